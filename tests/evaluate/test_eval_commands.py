"""`pano-pipe report` and `pano-pipe render` as typer commands on a prepared run folder."""

from __future__ import annotations

import cv2
import pytest
import typer
from typer.testing import CliRunner

from evalhelpers import run_evaluate, write_train_artifact
from evaluation.commands import ablate_command, render_command, report_command, sweep_command

app = typer.Typer()
app.command("report")(report_command)
app.command("render")(render_command)
app.command("ablate")(ablate_command)
app.command("sweep")(sweep_command)


@pytest.fixture(scope="module")
def run(sim_scene, sim_model, tmp_path_factory):
    pytest.importorskip("stages.train", reason="the train stage is not in this checkout yet")
    run = tmp_path_factory.mktemp("cmdrun") / "run"
    write_train_artifact(run, sim_model, resolution=(16, 32))
    run_evaluate(sim_scene, run, fps_repeats=1, lpips=False)
    return run


def test_report_command(run, sim_scene):
    r = CliRunner().invoke(app, ["report", str(sim_scene.root), "--out", str(run)])
    assert r.exit_code == 0, r.output
    html = (run / "report" / "report.html").read_text()
    # one view's 6 maps + 4 colour bars, 2 training charts, floor plan, durations
    assert html.count("<img") == 14 and "Stage durations" in html
    md = (run / "report" / "report.md").read_text()
    assert "| now |" in md  # engine states joined in
    assert "test metrics:" in r.output


def test_report_command_names_training_views_when_the_scene_holds_none_out(run, sim_scene, tmp_path):
    """Without test views evaluate scores the training views (a fit): the command says so."""
    import json
    import shutil

    copy = tmp_path / "run"
    shutil.copytree(run, copy)
    artifact = copy / "evaluate" / "artifact.json"
    doc = json.loads(artifact.read_text())
    doc["data"].update(split="train", on_train_views=True)
    artifact.write_text(json.dumps(doc))
    r = CliRunner().invoke(app, ["report", str(sim_scene.root), "--out", str(copy)])
    assert r.exit_code == 0, r.output
    assert "train metrics:" in r.output and "test metrics" not in r.output


def test_report_command_without_run_folder(sim_scene, tmp_path):
    pytest.importorskip("stages.train", reason="the train stage is not in this checkout yet")
    r = CliRunner().invoke(app, ["report", str(sim_scene.root), "--out", str(tmp_path / "nope")])
    assert r.exit_code != 0 and "no run folder" in str(r.exception)


def test_render_command(run, sim_scene):
    r = CliRunner().invoke(app, ["render", str(sim_scene.root), "--out", str(run), "--frames", "3",
                                 "--perspective", "--height", "12"])
    assert r.exit_code == 0, r.output
    video = run / "render" / "flythrough-train-persp.mp4"
    cap = cv2.VideoCapture(str(video))
    assert cap.get(cv2.CAP_PROP_FRAME_COUNT) == 3 and cap.get(cv2.CAP_PROP_FRAME_HEIGHT) == 12
    r = CliRunner().invoke(app, ["render", str(sim_scene.root), "--out", str(run), "--frames", "2",
                                 "--path", "test_00"])
    assert r.exit_code == 0, r.output
    cap = cv2.VideoCapture(str(run / "render" / "flythrough-test_00-pano.mp4"))
    assert (cap.get(cv2.CAP_PROP_FRAME_WIDTH), cap.get(cv2.CAP_PROP_FRAME_HEIGHT)) == (32, 16)


def test_render_command_needs_training(sim_scene, tmp_path):
    pytest.importorskip("stages.train", reason="the train stage is not in this checkout yet")
    r = CliRunner().invoke(app, ["render", str(sim_scene.root), "--out", str(tmp_path)])
    assert r.exit_code != 0 and "train first" in str(r.exception)


class _GridStarted(Exception):
    pass


def test_ablate_paper_says_what_it_will_cost_before_it_starts(run, sim_scene, monkeypatch):
    import evaluation.experiments

    def grid_started(*args, **kwargs):
        raise _GridStarted

    monkeypatch.setattr(evaluation.experiments, "run_ablation", grid_started)
    r = CliRunner().invoke(app, ["ablate", str(sim_scene.root), "--out", str(run), "--paper"])
    assert isinstance(r.exception, _GridStarted)  # the line below came first
    # 4 variants + the equal-time row, 3 seeds; the run's training: 1 s for 50 iterations at 16x32
    seconds = 15 * 7000 * (1.0 / 50) * (512 / 16) ** 2
    assert "ablate: 15 trainings of 7000 iterations at 512x1024 (H×W)" in r.output
    assert f"about {seconds / 3600:.1f} h on this machine" in r.output


def test_ablate_without_an_earlier_training_says_how_to_get_an_estimate(sim_scene, tmp_path, monkeypatch):
    import evaluation.experiments

    monkeypatch.setattr(evaluation.experiments, "run_ablation", lambda *a, **k: (_ for _ in ()).throw(_GridStarted))
    r = CliRunner().invoke(app, ["ablate", str(sim_scene.root), "--out", str(tmp_path / "R"), "--seeds", "2",
                                 "--equal", "none", "--iterations", "10"])
    assert isinstance(r.exception, _GridStarted)
    assert "8 trainings of 10 iterations" in r.output and "pano-pipe run train" in r.output
