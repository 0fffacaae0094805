"""Hardening, second pass (issue 21): one test per defect class, each failing before its fix.

Class 1 (links planted in run folders) is tests/pipeline/test_planted_links.py, class 2 (SIGTERM)
tests/pipeline/test_signals.py, class 4 (the viewer's socket) tests/viewer/test_viewer_hardening.py,
class 6 (Ray) tests/batch/test_ray_connect.py; the fuzz suite (tests/fuzz) generates more of each.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from simulate.generate import generate_scene
from tests import hostile_files as hostile
from tests.clitools import invoke, run_main

FAST = ["--set", "train.iterations=5", "--set", "train.height=8"]


def assert_one_line(code, out, err, *expected: str, exit_code: int = 2) -> str:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == exit_code, err
    assert "Traceback" not in out + err
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    for text in expected:
        assert text in lines[0], (text, lines[0])
    return lines[0]


def tree(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): (os.readlink(p).encode() if p.is_symlink() else p.read_bytes())
            for p in sorted(Path(root).rglob("*")) if p.is_symlink() or p.is_file()}


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("h2")
    generate_scene(root / "S", views=3, test_views=1, height=16, effects="none", with_layout=True, with_depth=True)
    assert run_main(["run", "all", root / "S", "--out", root / "R", *FAST]) == 0
    return root


@pytest.fixture
def run(tmp_path, finished_run, monkeypatch) -> Path:
    """tmp/S (the scene), tmp/R (a finished run), tmp/secret/ (outside both), cwd tmp/cwd."""
    shutil.copytree(finished_run / "S", tmp_path / "S")
    shutil.copytree(finished_run / "R", tmp_path / "R")
    (tmp_path / "secret").mkdir()
    (tmp_path / "secret" / "key.png").write_bytes((tmp_path / "S" / "images" / "train_00.png").read_bytes())
    (tmp_path / "secret" / "log.jsonl").write_text('{"iteration": 1, "loss": 0.5}\n')
    (tmp_path / "cwd").mkdir()
    monkeypatch.chdir(tmp_path / "cwd")
    return tmp_path


def _edit_artifact(path: Path, change) -> None:
    doc = json.loads(path.read_text())
    change(doc["data"])
    path.write_text(json.dumps(doc))


# ----------------------------------------------------------------------------- 3. files named by artifacts
@pytest.mark.parametrize("named", ["abs", "dotdot"])
def test_report_refuses_an_evaluate_artifact_naming_a_file_outside(run, named, capsys):
    secret = run / "secret" / "key.png"
    rel = str(secret) if named == "abs" else "../../secret/key.png"
    _edit_artifact(run / "R" / "evaluate" / "artifact.json", lambda d: d["views"][0].update(gt=rel))
    code, out, err = invoke(["report", run / "S", "--out", run / "R"], capsys)
    assert_one_line(code, out, err, "evaluate/artifact.json", "run folder")
    html = run / "R" / "report" / "report.html"
    assert not html.exists() or secret.read_bytes()[:64] not in html.read_bytes()
    assert not any(p.read_bytes() == secret.read_bytes() for p in (run / "R").rglob("*.png") if p.is_file()
                   and "evaluate" not in p.parts and "images" not in p.parts)


def test_report_refuses_a_train_log_outside(run, capsys):
    _edit_artifact(run / "R" / "train" / "artifact.json", lambda d: d.update(log=str(run / "secret" / "log.jsonl")))
    code, out, err = invoke(["report", run / "S", "--out", run / "R"], capsys)
    assert_one_line(code, out, err, "train/artifact.json", "absolute")


def test_render_refuses_a_model_named_outside(run, capsys):
    _edit_artifact(run / "R" / "train" / "artifact.json", lambda d: d.update(ply="../../secret/key.png"))
    code, out, err = invoke(["render", run / "S", "--out", run / "R", "--frames", "2"], capsys)
    assert_one_line(code, out, err, "leaves the run folder")


# ----------------------------------------------------------------------------- 5. importers' limits
def _nerfstudio(tmp: Path, depth_name: str, depth_bytes: bytes) -> Path:
    src = tmp / "ns"
    (src / "images").mkdir(parents=True)
    (src / "depth").mkdir()
    img = np.full((16, 32, 3), 120, np.uint8)
    frames = []
    for i in range(2):
        cv2.imwrite(str(src / "images" / f"f{i}.png"), img)
        (src / "depth" / f"f{i}{Path(depth_name).suffix}").write_bytes(depth_bytes)
        pose = np.eye(4)
        pose[0, 3] = i
        frames.append({"file_path": f"images/f{i}.png", "depth_file_path": f"depth/f{i}{Path(depth_name).suffix}",
                       "transform_matrix": pose.tolist()})
    (src / "transforms.json").write_text(json.dumps({"camera_model": "EQUIRECTANGULAR", "w": 32, "h": 16,
                                                     "frames": frames}))
    return src / "transforms.json"


@pytest.mark.parametrize("kind, data, expected", [
    ("png", hostile.png(16000, 8000, bit_depth=16), "megapixels"),
    ("npy", hostile.npy((8000, 16000)), "header claims"),
    ("npy", hostile.npy((8000, 16000), payload=8000 * 16000 * 4 // 1000, header_pad=20000), "header"),
    ("exr", hostile.exr(16000, 8000), "megapixels"),
])
def test_import_nerfstudio_checks_depth_headers(tmp_path, capsys, kind, data, expected):
    transforms = _nerfstudio(tmp_path, f"d.{kind}", data)
    code, out, err = invoke(["import-nerfstudio", transforms, tmp_path / "out", "--scale", "1"], capsys)
    assert_one_line(code, out, err, expected)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("name, data, expected", [
    ("points3D.bin", hostile.colmap_points3d(2 ** 40), "track entries"),
    ("images.bin", hostile.colmap_images(2 ** 40), "2D points"),
    ("cameras.bin", hostile.colmap_cameras(64, 32, cameras=2 ** 50), "cameras"),
    ("cameras.bin", hostile.colmap_cameras(200000, 100000), "megapixels"),
])
def test_import_colmap_checks_binary_counts(tmp_path, capsys, name, data, expected):
    from tests.pipeline.test_import_metric import sfm_frame, true_poses, write_model

    model = write_model(tmp_path / "sparse" / "0", true_poses(), sfm_frame(), 0.37)
    (model / name).write_bytes(data)
    (tmp_path / "images").mkdir()
    code, out, err = invoke(["import-colmap", model, tmp_path / "images", tmp_path / "out", "--scale", "1"], capsys)
    assert_one_line(code, out, err, name, expected)
    assert not (tmp_path / "out").exists()


# ----------------------------------------------------------------------------- 8. bad input, not internal errors
@pytest.mark.parametrize("folder", ["scan 10:30", "-scan", ".scan"])
def test_scene_folder_names_that_cannot_name_a_run_folder(tmp_path, finished_run, capsys, monkeypatch, folder):
    shutil.copytree(finished_run / "S", tmp_path / folder)
    doc = json.loads((tmp_path / folder / "scene.json").read_text())
    doc.pop("name", None)
    (tmp_path / folder / "scene.json").write_text(json.dumps(doc))
    monkeypatch.chdir(tmp_path)
    for command in (["run", "all"], ["status"], ["clean"]):
        code, out, err = invoke([*command, f"./{folder}"], capsys)
        assert_one_line(code, out, err, "scene name", "scene.json")
    assert not (tmp_path / "runs").exists()
    # given a run folder, the name does not matter
    code, out, err = invoke(["run", "layout", f"./{folder}", "--out", tmp_path / "R"], capsys)
    assert code == 0, err


def test_a_ply_claiming_a_trillion_vertices(run, capsys):
    ply = run / "R" / "train" / "point_cloud.ply"
    ply.write_bytes(hostile.ply(10 ** 12))
    for args in (["export", run / "R", "--format", "splat"], ["render", run / "S", "--out", run / "R", "--frames", "2"],
                 ["view", run / "R", "--port", "1"]):
        code, out, err = invoke(args, capsys)
        assert_one_line(code, out, err, "point_cloud.ply", "vertices")


def test_report_on_a_depth_npy_with_a_huge_header(run, capsys):
    npy = run / "R" / "evaluate" / json.loads((run / "R" / "evaluate" / "artifact.json").read_text())[
        "data"]["views"][0]["depth_npy"]
    npy.write_bytes(hostile.npy((10 ** 6, 10 ** 6), header_pad=30000))
    code, out, err = invoke(["report", run / "S", "--out", run / "R"], capsys)
    assert code == 0 and not err.strip(), err
    assert "unreadable" in (run / "R" / "report" / "report.md").read_text()


def test_report_img_as_a_link(run, capsys):
    (run / "R" / "report").mkdir(exist_ok=True)
    shutil.rmtree(run / "R" / "report" / "img", ignore_errors=True)
    (run / "R" / "report" / "img").symlink_to(run / "secret")
    before = tree(run / "secret")
    code, out, err = invoke(["report", run / "S", "--out", run / "R"], capsys)
    assert_one_line(code, out, err, "report/img", "symbolic link")
    assert tree(run / "secret") == before


# ----------------------------------------------------------------------------- 9. stderr holds the error line only
def test_no_numpy_warnings_on_stderr(run, tmp_path, capsys):
    from tests.pipeline.test_import_metric import sfm_frame, true_poses, write_model

    model = write_model(tmp_path / "sparse" / "0", true_poses(), sfm_frame(), 0.37)
    (tmp_path / "images").mkdir()
    for name in true_poses():
        cv2.imwrite(str(tmp_path / "images" / f"{name}.png"), np.zeros((32, 64, 3), np.uint8))
    code, out, err = invoke(["import-colmap", model, tmp_path / "images", tmp_path / "out", "--scale", "1e300"],
                            capsys)
    assert_one_line(code, out, err, "over 100000 m")
    # a model with NaN colours: refused in one line, no numpy warning (issue 37, item 2)
    ply = run / "R" / "train" / "point_cloud.ply"
    hostile.nan_model(ply)
    for fmt in ("splat", "spz"):
        code, out, err = invoke(["export", run / "R", "--format", fmt], capsys)
        assert_one_line(code, out, err, "point_cloud.ply", "NaN")


# ----------------------------------------------------------------------------- 10. a batch names run folders as a run does
def test_a_batch_refuses_the_scene_names_a_run_refuses(tmp_path, finished_run, capsys):
    scenes = tmp_path / "scenes"
    for name in ("good", "scan 10:30"):
        shutil.copytree(finished_run / "S", scenes / name)
        doc = json.loads((scenes / name / "scene.json").read_text())
        doc.pop("name", None)
        (scenes / name / "scene.json").write_text(json.dumps(doc))
    code, out, err = invoke(["run", "layout", scenes, "--out", tmp_path / "runs"], capsys)
    assert code == 1
    assert "scan 10:30" in out and "scene name" in out
    assert sorted(p.name for p in (tmp_path / "runs").iterdir()) == ["good"]


# ----------------------------------------------------------------------------- 11. OUT = the working folder
def test_importers_refuse_the_working_folder_as_out(tmp_path, capsys, monkeypatch):
    transforms = _nerfstudio(tmp_path, "d.npy", hostile.real_npy(np.ones((16, 32), np.float32)))
    empty = tmp_path / "empty"
    empty.mkdir()
    monkeypatch.chdir(empty)
    code, out, err = invoke(["import-nerfstudio", transforms, ".", "--scale", "1"], capsys)
    assert_one_line(code, out, err, "working folder")
    assert list(empty.iterdir()) == []


# ----------------------------------------------------------------------------- 12. report.md escapes HTML
def test_report_md_escapes_html_from_artifacts(run, capsys):
    sweep = run / "R" / "sweep"
    sweep.mkdir()
    cv2.imwrite(str(sweep / "sweep.png"), np.zeros((8, 8, 3), np.uint8))
    (sweep / "sweep.json").write_text(json.dumps({"notes": ['<img src=x onerror="alert(1)"> & <b>bold</b>']}))
    (sweep / "sweep.md").write_text("| a<script> | b |\n|---|---|\n| <i>1</i> | 2 |\n")
    code, out, err = invoke(["report", run / "S", "--out", run / "R"], capsys)
    assert code == 0, err
    md = (run / "R" / "report" / "report.md").read_text()
    html = (run / "R" / "report" / "report.html").read_text()
    for text in (md, html):
        assert "<img src=x" not in text and "<script>" not in text and "<i>1</i>" not in text
    assert "&lt;img src=x onerror=" in md and "&lt;i&gt;1&lt;/i&gt;" in md


# ----------------------------------------------------------------------------- 13. clean --out LINK
def test_clean_refuses_a_linked_run_folder(run, capsys):
    (run / "link").symlink_to(run / "R")
    before = tree(run / "R")
    code, out, err = invoke(["clean", run / "S", "--out", run / "link"], capsys)
    assert_one_line(code, out, err, "symbolic link")
    assert tree(run / "R") == before and (run / "link").is_symlink()


# ----------------------------------------------------------------------------- 7. mirrored poses
def test_given_poses_that_only_fit_mirrored_are_refused():
    from sfm.frame import align_to_known

    rng = np.random.default_rng(0)
    recovered, mirrored, same = {}, {}, {}
    for i in range(4):
        pose = np.eye(4)
        pose[:3, 3] = rng.normal(size=3)
        recovered[f"v{i}"] = pose
        m = pose.copy()
        m[:3, 3] = -2.0 * pose[:3, 3]  # the positions reflected through the origin, rotations as recovered
        mirrored[f"v{i}"] = m
        s = pose.copy()
        s[:3, 3] = 2.0 * pose[:3, 3]
        same[f"v{i}"] = s
    order = sorted(recovered)
    heights = dict.fromkeys(order, 1.5)
    fit = align_to_known(recovered, same, np.zeros((0, 3)), heights, order)
    assert fit.transform.scale == pytest.approx(2.0)
    with pytest.raises(ValueError, match="mirrored"):
        align_to_known(recovered, mirrored, np.zeros((0, 3)), heights, order)
