"""Issue 36, item 4: a run without priors says what it costs (banner, summary, report), a model that
overfits says so with the likely causes in order, and every stage warning is in the report beside
its stage. Tiny simulated scenes, training of a few iterations."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import pytest

from evaluation.diagnosis import (OVERFIT_GAP_DB, ViewSpacing, no_priors_message, overfit_message,
                                  plans_without_priors, trained_without_priors)
from evaluation.report import build_report
from evaluation.report_text import md_text
from pipeline.engine import Engine, read_artifact, topological_order
from pipeline.registry import build_registry
from schemas.scene_loader import load_scene
from simulate.generate import generate_scene
from tests.clitools import invoke, run_main

FAST = ["--set", "train.iterations=5", "--set", "train.height=8", "--set", "evaluate.fps_repeats=1",
        "--set", "evaluate.lpips=false"]


@pytest.fixture(scope="module")
def bare(tmp_path_factory) -> Path:
    """A finished run of a scene without layout or depth (no files, no model): folder with S/ and R/."""
    root = tmp_path_factory.mktemp("bare")
    generate_scene(root / "S", views=2, test_views=1, height=16, effects="none")
    assert run_main(["run", "all", root / "S", "--out", root / "R", *FAST]) == 0
    return root


@pytest.fixture
def run(bare, tmp_path, monkeypatch) -> Path:
    shutil.copytree(bare / "S", tmp_path / "S")
    shutil.copytree(bare / "R", tmp_path / "R")
    monkeypatch.chdir(tmp_path)
    return tmp_path


def _flat(text: str) -> str:
    return " ".join(text.split())


def _set_train_psnr(run_dir: Path, value: float) -> None:
    """The train artifact's training PSNR set by hand (its cache key unchanged: a later run finds it cached)."""
    path = run_dir / "train" / "artifact.json"
    art = json.loads(path.read_text())
    art["data"]["final_train_psnr"] = value
    path.write_text(json.dumps(art))


def test_banner_summary_and_report_say_a_run_without_priors_costs(run, capsys):
    code, out, err = invoke(["run", "all", run / "S", "--out", run / "R", *FAST, "--force"], capsys)
    assert code == 0, err
    text = _flat(out)
    message = _flat(no_priors_message())
    # the banner, before any stage, and the summary, after the metrics
    assert text.index(message) < text.index("▶ train")
    assert text.count(message) == 2 and text.rindex(message) > text.index("metrics (test views")
    for said in ("training starts from random points", "dB of held-out PSNR",
                 "pano-pipe models fetch horizonnet-zind", "pano-pipe models fetch depth-anything-v2-small",
                 'docs/evaluation.md, "Runs without priors"'):
        assert said in message
    code, out, err = invoke(["report", run / "S", "--out", run / "R", *FAST], capsys)
    assert code == 0, err
    md = _flat((run / "R" / "report" / "report.md").read_text())
    assert "What limits this run" in md and "No priors: the layout and depth stages are both skipped" in md
    assert "pano-pipe models fetch horizonnet-zind" in md


def test_a_run_with_a_layout_says_nothing_of_priors(tmp_path, capsys):
    generate_scene(tmp_path / "S", views=2, test_views=1, height=16, effects="none", with_layout=True)
    code, out, err = invoke(["run", "all", tmp_path / "S", "--out", tmp_path / "R", *FAST], capsys)
    assert code == 0, err
    assert "no priors" not in out and "overfits" not in out
    r = build_report(tmp_path / "R", load_scene(tmp_path / "S"))
    assert "diagnosis" not in r.sections and "No priors" not in r.markdown.read_text()


def test_a_model_that_overfits_says_so_with_the_causes_in_order(run, capsys):
    heldout = read_artifact(run / "R", "evaluate").data.mean["psnr"]
    _set_train_psnr(run / "R", heldout + OVERFIT_GAP_DB + 2)
    code, out, err = invoke(["run", "all", run / "S", "--out", run / "R", *FAST], capsys)
    assert code == 0, err
    assert re.search(r"train\s*│\s*cached", out)  # the numbers of the run, not a new one
    text = _flat(out)
    assert "the model overfits the training views: held-out PSNR" in text
    said = text[text.index("the model overfits"):]
    first, second = said.index("1. no priors"), said.index("2. too few or too distant views: 2 training panoramas")
    assert first < second and "held-out views" in said
    code, out, err = invoke(["report", run / "S", "--out", run / "R", *FAST], capsys)
    md = _flat((run / "R" / "report" / "report.md").read_text())
    assert "The model overfits the training views" in md and "1. no priors" in md


def test_a_gap_below_the_threshold_is_no_overfit(run, capsys):
    heldout = read_artifact(run / "R", "evaluate").data.mean["psnr"]
    _set_train_psnr(run / "R", heldout + OVERFIT_GAP_DB - 0.5)
    code, out, err = invoke(["run", "all", run / "S", "--out", run / "R", *FAST], capsys)
    assert code == 0 and "overfits" not in out


def test_overfit_message_rules():
    spacing = ViewSpacing(n_train=4, train_neighbour_m=3.1, test_to_train_m=2.2)
    msg = overfit_message(43.2, 15.5, "test", True, spacing)
    assert msg.startswith("the model overfits the training views: held-out PSNR 15.5 dB is 27.7 dB below")
    assert msg.index("1. no priors") < msg.index("2. too few or too distant views: 4 training panoramas, 3.10 m")
    # with priors, the views come first; no message below the gap, without numbers, or on the training views
    assert "1. too few or too distant views" in overfit_message(43.2, 15.5, "test", False, spacing)
    assert overfit_message(30.0, 30.0 - OVERFIT_GAP_DB + 0.1, "test", True) is None
    assert overfit_message(30.0, 30.0 - OVERFIT_GAP_DB, "test", True) is not None
    assert overfit_message(None, 15.5, "test", True) is None
    assert overfit_message(40.0, float("nan"), "test", True) is None
    assert overfit_message(43.2, 15.5, "train", True) is None


def test_no_priors_is_read_from_what_training_started_from():
    skipped = {"poses": "skipped", "align": "skipped", "sampling": "skipped", "union": "skipped"}
    assert trained_without_priors("random", skipped)
    assert not trained_without_priors("random", {**skipped, "sampling": "k"})  # random asked for beside a layout
    assert not trained_without_priors("depth", {**skipped, "align": "k"})
    assert not trained_without_priors("random", {})  # not known


def test_the_plan_of_a_bare_scene_is_without_priors(run):
    engine = Engine(load_scene(run / "S"), run / "R", build_registry())
    plans = engine.plan()
    assert plans_without_priors(plans, engine.select())
    assert not plans_without_priors(plans, engine.select(until="union"))  # trains nothing


def test_every_stage_warning_is_in_the_report_beside_its_stage(tmp_path):
    """Warnings of real stages (layout: a camera height assumed; union, sampling, evaluate: whatever
    they say) are persisted in their artifacts (meta.warnings, read typed) and all in the report."""
    generate_scene(tmp_path / "S", views=2, test_views=1, height=16, effects="none", with_layout=True)
    doc = json.loads((tmp_path / "S" / "scene.json").read_text())
    for v in doc["views"]:
        v.pop("camera_height", None)  # the layout stage assumes one and says so
    (tmp_path / "S" / "scene.json").write_text(json.dumps(doc))
    assert run_main(["run", "all", tmp_path / "S", "--out", tmp_path / "R", *FAST,
                     "--set", "evaluate.lpips=true", "--set", "evaluate.lpips_weights=no-such-folder"]) == 0
    said = [(stage, w) for stage in topological_order(build_registry())
            if (art := read_artifact(tmp_path / "R", stage)) is not None for w in art.meta.warnings]
    stages = {stage for stage, _ in said}
    assert "layout" in stages and "evaluate" in stages, said
    assert any("assumed" in w for stage, w in said if stage == "layout")
    r = build_report(tmp_path / "R", load_scene(tmp_path / "S"))
    assert "warnings" in r.sections
    md = r.markdown.read_text()
    table = md[md.index("## Stage warnings"):]
    for stage, w in said:
        assert f"| {stage} | {md_text(w)} |" in table
    # LPIPS's reason is said among the warnings; the metrics point there rather than repeat it
    reason = md_text(read_artifact(tmp_path / "R", "evaluate").data.lpips_reason)
    metrics = md[md.index("## Test metrics"):md.index("## Views")]
    assert reason in table and reason not in metrics and "LPIPS unavailable: see the evaluate stage's warning" in metrics
