"""The command line says what it does: typed --set values, parameter listings, reasons,
the run header and summary, plain progress lines, where benchmarks write."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from pipeline import cli
from tests.clitools import invoke, run_main, without_kernel_notices
from runtime.console import PlainProgress
from simulate.generate import generate_scene

FAST = ["--set", "train.iterations=5", "--set", "train.height=8", "--set", "evaluate.fps_repeats=1"]


def run_cli(args, capsys) -> tuple[int, str, str]:
    return invoke(args, capsys)


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("ux")
    generate_scene(root / "S", views=3, test_views=2, height=16, effects="none", with_layout=True, with_depth=True)
    assert run_main(["run", "all", root / "S", "--out", root / "R", *FAST]) == 0
    return root


@pytest.fixture
def run(finished_run, tmp_path, monkeypatch) -> Path:
    shutil.copytree(finished_run / "S", tmp_path / "S")
    shutil.copytree(finished_run / "R", tmp_path / "R")
    monkeypatch.chdir(tmp_path)
    return tmp_path


def outcomes(out: str) -> dict[str, str]:
    rows = {}
    for line in out.splitlines():
        cells = [c.strip() for c in line.split("│") if c.strip()]
        if len(cells) >= 2 and cells[1] in ("ran", "cached", "skipped", "failed"):
            rows[cells[0]] = cells[1]
    return rows


def test_set_values_are_typed_by_the_parameter_schema():
    config, _ = cli.load_config(None, ["train.projection=360", "train.iterations=7", "train.extent=null",
                                       "train.background=[0, 0, 0]", "train.layout_reg=false"])
    assert config["train"] == {"projection": "360", "iterations": 7, "extent": None, "background": [0, 0, 0],
                               "layout_reg": False}


def test_projection_360_is_accepted_on_the_command_line(run, capsys):
    code, out, err = run_cli(["status", run / "S", "--out", run / "R", *FAST, "--set", "train.projection=360"],
                             capsys)
    assert code == 0, err


def test_unknown_parameter_names_the_closest_few_and_the_params_command(run, capsys):
    code, out, err = run_cli(["status", run / "S", "--out", run / "R", "--set", "train.iteratoins=1"], capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1
    assert "iteratoins: unknown parameter (did you mean iterations?); the closest: iterations," in err
    assert "(`pano-pipe params train` lists all" in err and "projection" not in err


def test_run_stage_force_reruns_only_that_stage(run, capsys):
    code, out, err = run_cli(["run", "evaluate", run / "S", "--out", run / "R", *FAST, "--force"], capsys)
    assert code == 0, err
    rows = outcomes(out)
    assert rows["evaluate"] == "ran" and rows["train"] == "cached" and rows["layout"] == "cached"
    code, out, err = run_cli(["run", "evaluate", run / "S", "--out", run / "R", *FAST, "--force-upstream"], capsys)
    assert code == 0, err
    rows = outcomes(out)
    assert rows.pop("poses") == "skipped"  # every view has a pose
    assert set(rows.values()) == {"ran"}


def test_status_always_says_why(run, capsys):
    code, out, err = run_cli(["status", run / "S", "--out", run / "R", *FAST], capsys)
    assert code == 0
    from pipeline.cli import make_engine

    plans = make_engine(run / "S", run / "R", None, FAST[1::2]).plan()
    assert all(p.reason for p in plans.values())
    assert plans["train"].state == "up-to-date" and "unchanged" in plans["train"].reason


def test_params_lists_type_default_and_description(capsys):
    code, out, err = run_cli(["params", "train"], capsys)
    assert code == 0
    flat = " ".join(out.split())
    assert "train.projection" in flat and all(f"'{p}'" in flat for p in ("360", "crops", "cubemap")) and "train.iterations" in flat
    assert "layout.model" not in out
    code, out, err = run_cli(["params"], capsys)
    assert all(f"{stage}." in out for stage in ("layout", "depth", "union", "sampling", "align", "train",
                                                "evaluate"))
    code, out, err = run_cli(["params", "bogus"], capsys)
    assert code == 2 and "unknown stage 'bogus'" in err


def test_run_prints_a_header_and_a_summary_with_per_view_metrics(run, capsys):
    code, out, err = run_cli(["run", "all", run / "S", "--out", run / "R", *FAST], capsys)
    assert code == 0 and without_kernel_notices(err) == ""
    first = out.splitlines()[0]
    assert first.startswith("scene S: 5 views (3 train, 2 test); training at 8x16") and str(run / "R") in out
    import torch

    # the device training really runs on (issue 35: a GPU machine read "cuda (training runs on the CPU)")
    assert f"on {'cuda' if torch.cuda.is_available() else 'cpu'};" in first and "runs on the CPU" not in first
    assert "model: " in out and "point_cloud.ply" in out and "Gaussians" in out
    assert "test_00" in out and "test_01" in out and "mean" in out  # one row per test view
    assert f"pano-pipe report {run / 'S'} --out {run / 'R'}" in " ".join(out.split())
    next_steps = out[out.index("next steps:"):]  # after the summary, each a command to copy
    assert f"pano-pipe view {run / 'S'} --out {run / 'R'}" in next_steps
    assert f"pano-pipe export {run / 'R'} --format ply" in next_steps


def test_an_up_to_date_named_stage_is_cached_unless_forced(run, capsys):
    code, out, err = run_cli(["run", "evaluate", run / "S", "--out", run / "R", *FAST], capsys)
    assert code == 0, err
    rows = outcomes(out)
    assert rows["evaluate"] == "cached" and set(rows.values()) <= {"cached", "skipped"}
    import typer

    run_command = typer.main.get_command(cli.app).commands["run"]
    force_help = next(p.help for p in run_command.params if p.name == "force")
    assert "even if it is up to date" in force_help and "reported cached" in run_command.help  # as it behaved


def test_plain_progress_prints_periodic_lines(capsys):
    with PlainProgress(every_s=0.0) as progress:
        task = progress.add_task("train", total=4, loss="-")
        for i in range(4):
            progress.update(task, completed=i + 1, loss=f"{0.5 / (i + 1):.3f}")
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 4 and lines[-1].startswith("train: 4/4 (100%)") and "loss 0.125" in lines[-1]
    assert "ETA" not in lines[0] and "ETA" in lines[1]  # the rate is timed from the first step on


def test_plain_progress_is_quiet_between_periods(capsys):
    with PlainProgress(every_s=3600) as progress:
        task = progress.add_task("layout", total=100)
        for _ in range(100):
            progress.advance(task)
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines == [lines[0]] and lines[0].startswith("layout: 100/100 (100%)")


def test_upsampled_training_images_are_warned_about(run, capsys):
    code, out, err = run_cli(["run", "train", run / "S", "--out", run / "R", "--set", "train.iterations=2",
                              "--set", "train.height=32"], capsys)
    assert code == 0, err
    flat = " ".join(out.split())
    assert "warning: 3 training image(s) smaller than the training size 64x32, upsampled" in flat


def test_benchmarks_write_where_they_are_told_never_into_docs(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    from pipeline.bench_commands import BENCH_OUT

    assert not str(BENCH_OUT).startswith("docs")
    code, out, err = run_cli(["bench", "batch", "--scenes", "1", "--iterations", "2", "--executors", "local",
                              "--out", tmp_path / "b"], capsys)
    assert code == 0, err
    assert (tmp_path / "b" / "bench_batch.md").is_file() and json.loads(
        (tmp_path / "b" / "bench_batch.json").read_text())["rows"][0]["executor"] == "local"
    assert not (tmp_path / "docs").exists()
