"""The report's stage sections (layout overlay, depth alignment) are there when their stage ran and
absent otherwise; exports are linked; the configuration puts changed values first and names the
settings that had no effect; durations follow the DAG; error maps are grey where masked."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from evaluation.report import build_report, stage_durations
from evaluation.report_sections import boundary_rows, settings_without_effect, stage_file
from schemas.scene_loader import load_scene
from simulate.generate import generate_scene
from tests.clitools import run_main

FAST = ["--set", "train.iterations=4", "--set", "train.height=16", "--set", "evaluate.fps_repeats=1",
        "--set", "evaluate.lpips=false"]


def _scene_with_nadir_cap(path: Path, **kwargs) -> Path:
    generate_scene(path, views=2, test_views=1, height=16, effects="none", **kwargs)
    doc = json.loads((path / "scene.json").read_text())
    doc["nadir_mask_deg"] = 40.0  # the metrics leave out the bottom of every panorama
    (path / "scene.json").write_text(json.dumps(doc))
    return path


@pytest.fixture(scope="module")
def full_run(tmp_path_factory) -> tuple[Path, Path]:
    """A run of every stage (layout and depth given): (scene, run)."""
    root = tmp_path_factory.mktemp("sections")
    scene = _scene_with_nadir_cap(root / "S", with_layout=True, with_depth=True)
    assert run_main(["run", "all", scene, "--out", root / "R", *FAST]) == 0
    return scene, root / "R"


@pytest.fixture(scope="module")
def bare_run(tmp_path_factory) -> tuple[Path, Path]:
    """A run without layout or depth: random init, no layout / union / sampling / align stage."""
    root = tmp_path_factory.mktemp("bare")
    scene = _scene_with_nadir_cap(root / "S")
    assert run_main(["run", "all", scene, "--out", root / "R", *FAST, "--set", "train.appearance=true",
                     "--set", "train.crop_fov=90"]) == 0
    return scene, root / "R"


def test_layout_and_alignment_sections_when_their_stages_ran(full_run, tmp_path):
    scene_dir, run = full_run
    scene = load_scene(scene_dir)
    r = build_report(run, scene, out_dir=tmp_path / "rep")
    assert r.sections.index("floorplan") < r.sections.index("layout") < r.sections.index("alignment")
    md = r.markdown.read_text()
    train = [v.name for v in scene.views if v.split == "train"]
    for name in train:  # one overlay per training panorama, none for the test view
        png = tmp_path / "rep" / "img" / f"layout-{name}.png"
        assert png.is_file() and cv2.imread(str(png)) is not None
        assert f"layout-{name}.png" in md
    assert not list((tmp_path / "rep" / "img").glob("layout-test*"))
    align = json.loads((run / "align" / "artifact.json").read_text())["data"]
    assert "## Depth alignment" in md and f"{align['scale']:.4g}" in md
    assert f"{100 * align['inlier_share']:.1f}% of the labelled pixels agree" in md


def test_stage_sections_absent_when_their_stages_did_not_run(bare_run, tmp_path):
    scene_dir, run = bare_run
    r = build_report(run, load_scene(scene_dir), out_dir=tmp_path / "rep")
    assert "layout" not in r.sections and "alignment" not in r.sections
    md = r.markdown.read_text()
    assert "Layout on the training panoramas" not in md and "Depth alignment" not in md


def test_boundaries_land_on_the_rows_of_their_latitudes():
    lat = np.array([[np.pi / 4] * 8, [-np.pi / 6] * 8])
    cols, rows = boundary_rows(lat, 64)
    assert cols[0] == pytest.approx(0.5 * 128 / 8 - 0.5) and cols[-1] == pytest.approx(127.5 - 0.5 * 128 / 8)
    assert rows[0, 0] == pytest.approx(64 / 4 - 0.5) and rows[1, 0] == pytest.approx(64 * (0.5 + 1 / 6) - 0.5)


def test_settings_without_effect_are_named_with_their_reason(bare_run, tmp_path):
    scene_dir, run = bare_run
    scene = load_scene(scene_dir)
    found = settings_without_effect(run, scene)
    assert "no layout cloud" in found[("train", "layout_reg")]
    assert "one training panorama" not in found.get(("train", "appearance"), "")  # two panoramas differ
    assert "crops" in found[("train", "crop_fov")]
    md = build_report(run, scene, out_dir=tmp_path / "rep").markdown.read_text()
    assert "Settings that had no effect" in md and "| train.layout_reg | true | no layout cloud" in md
    assert re.search(r"\| train\.layout_reg \| true \|[^|]*\| not applied: no layout cloud", md)
    assert "| layout regularisation | yes (not applied: no layout cloud" in md  # the training summary too


def test_layout_regularisation_counts_as_applied_with_a_layout(full_run):
    scene_dir, run = full_run
    assert ("train", "layout_reg") not in settings_without_effect(run, load_scene(scene_dir))


def test_appearance_with_one_training_panorama_had_nothing_to_differ(tmp_path):
    scene = generate_scene(tmp_path / "S", views=1, test_views=0, height=16, effects="none")
    del scene
    assert run_main(["run", "train", tmp_path / "S", "--out", tmp_path / "R", "--set", "train.iterations=2",
                     "--set", "train.height=8", "--set", "train.appearance=true"]) == 0
    found = settings_without_effect(tmp_path / "R", load_scene(tmp_path / "S"))
    assert "one training panorama" in found[("train", "appearance")]


def test_configuration_lists_changed_values_first_and_folds_the_rest(full_run, tmp_path):
    scene_dir, run = full_run
    md = build_report(run, load_scene(scene_dir), out_dir=tmp_path / "rep").markdown.read_text()
    config = md[md.index("## Configuration"):md.index("## Stage durations")]
    first_table, folded = config.split("<details>", 1)
    assert "| train.iterations | 4 | 2000 | changed |" in first_table  # the fast preset's 2,000 as the default
    assert "| evaluate.lpips | false | true | changed |" in first_table
    assert "train.lr_opacity" not in first_table  # at its default: only in the folded table
    assert "train.lr_opacity" in folded and "</details>" in folded
    # settings left unset show the value training used (the preset's, the projection's), as their
    # default: not null (issue 40)
    assert "| train.max_gaussians | 50000 | 50000 |" in folded and "| train.eps2d | 0.05 | 0.05 |" in folded
    assert "| train.random_turns | true | true |" in folded and "| train.lambda_layout | null" not in config
    html = (tmp_path / "rep" / "report.html").read_text()
    assert "<details><summary>all " in html


def test_durations_follow_the_dag_poses_first(full_run):
    _, run = full_run
    assert [r["stage"] for r in stage_durations(run)] == ["poses", "layout", "depth", "union", "sampling",
                                                          "align", "train", "evaluate"]


def test_error_maps_are_grey_where_the_metrics_leave_pixels_out(full_run):
    _, run = full_run
    ev = json.loads((run / "evaluate" / "artifact.json").read_text())["data"]
    err = cv2.cvtColor(cv2.imread(str(run / "evaluate" / ev["views"][0]["error"])), cv2.COLOR_BGR2RGB)
    assert (err[-1] == 128).all()  # the bottom row lies inside the 40° nadir cap
    assert not (err[err.shape[0] // 2] == 128).all()  # the horizon is measured: coloured


def test_exports_and_videos_are_linked_when_they_exist(full_run, tmp_path):
    scene_dir, src = full_run
    run = tmp_path / "R"
    shutil.copytree(src, run)
    scene = load_scene(scene_dir)
    before = build_report(run, scene)
    assert not any("export/" in h or h.endswith(".mp4") for h in before.links)
    (run / "export").mkdir()
    for name in ("point_cloud.ply", "point_cloud.spz", "mesh.glb", ".tmp-partial.ply"):
        (run / "export" / name).write_bytes(b"x")
    (run / "render").mkdir()
    (run / "render" / "flythrough-train-pano.mp4").write_bytes(b"x")
    after = build_report(run, scene)
    exported = sorted(h.split("/")[-1] for h in after.links if "/export/" in h)
    assert exported == ["mesh.glb", "point_cloud.ply", "point_cloud.spz"]
    assert any(h.endswith("render/flythrough-train-pano.mp4") for h in after.links)
    md = after.markdown.read_text()
    assert "mesh.glb (room mesh, glTF binary; y up unless exported with --glb-axes pano-pipe)" in md
    assert "point_cloud.ply (3D Gaussians, standard 3DGS PLY; pano-pipe axes, y down)" in md


def test_stage_file_stays_inside_the_stage_folder(tmp_path):
    (tmp_path / "layout").mkdir()
    (tmp_path / "layout" / "a.npy").write_bytes(b"x")
    (tmp_path / "secret.npy").write_bytes(b"x")
    assert stage_file(tmp_path, "layout", "a.npy") == tmp_path / "layout" / "a.npy"
    for bad in ("../secret.npy", str(tmp_path / "secret.npy"), "", None, "..", "missing.npy"):
        assert stage_file(tmp_path, "layout", bad) is None
