"""The poses stage: panoramas without poses posed by structure from motion, upright and metric."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

import simulate
from pipeline.engine import Engine
from pipeline.registry import build_registry
from schemas.scene_loader import load_scene
from sfm.bench import unposed_copy
from sfm.frame import pose_errors, rotation_angle_deg
from tests.clitools import invoke, shared_data

ZIND = shared_data() / "zind_pair"
#: The cuboid scenes of the COLMAP tests: textured, furnished, shaded, with fine detail, no capture effects.
COLMAP_EFFECTS = "texture,furniture,shading,aa,detail"


def _simulated(tmp_path: Path, views: int, test_views: int = 0, height: int = 512, seed: int = 0):
    sim = tmp_path / f"sim{views}"
    simulate.generate_scene(sim, preset="cuboid", views=views, test_views=test_views, height=height, seed=seed,
                            effects=COLMAP_EFFECTS)
    scene = tmp_path / f"scene{views}"
    return scene, unposed_copy(sim, scene)


def _run_poses(scene: Path, run: Path, **params) -> dict:
    Engine(load_scene(scene), run, build_registry(), {"poses": params}).run(target="poses")
    return json.loads((run / "poses" / "artifact.json").read_text())["data"]


@pytest.mark.parametrize("views", [4, 8])
def test_simulated_scene_posed_by_colmap_within_2cm_and_half_a_degree(tmp_path, views):
    scene, truth = _simulated(tmp_path, views)
    data = _run_poses(scene, tmp_path / "run", method="equirect")
    posed = {v["view"]: np.asarray(v["pose"]) for v in data["views"] if v["registered"]}
    assert sorted(posed) == sorted(truth)
    errors = pose_errors(posed, truth)
    assert max(e[0] for e in errors.values()) < 0.02, errors
    assert max(e[1] for e in errors.values()) < 0.5, errors
    # upright without any rigid fit: every camera's down axis is gravity (+y)
    for pose in posed.values():
        assert np.degrees(np.arccos(np.clip(pose[1, 1], -1, 1))) < 0.5
    assert data["frame"] == "floor" and data["scale_uncertainty"] < 0.01
    assert data["floor_tilt_deg"] < 1.0
    assert all(v["reprojection_error_px"] < 1.0 for v in data["views"])
    assert (tmp_path / "run" / "poses" / data["sparse_points"]).stat().st_size > 1000
    assert (tmp_path / "run" / "poses" / data["drawing"]).is_file()


def test_given_poses_fix_the_frame(tmp_path):
    scene, truth = _simulated(tmp_path, 4)
    manifest = json.loads((scene / "scene.json").read_text())
    for v in manifest["views"][:2]:
        v["pose"] = truth[v["name"]].tolist()
    (scene / "scene.json").write_text(json.dumps(manifest))
    data = _run_poses(scene, tmp_path / "run", method="equirect")  # cameras at different heights
    assert data["frame"] == "known poses"
    views = {v["view"]: v for v in data["views"]}
    for name, pose in truth.items():  # no alignment at all: the given views define the world
        np.testing.assert_allclose(views[name]["pose"], pose, atol=0.02)
    given = [v for v in views.values() if v["given"]]
    assert len(given) == 2 and all(v["residual_m"] < 0.02 and v["residual_deg"] < 0.5 for v in given)


def test_downstream_stages_see_the_recovered_poses(tmp_path):
    scene, truth = _simulated(tmp_path, 4)
    engine = Engine(load_scene(scene), tmp_path / "run", build_registry(), {"poses": {"method": "equirect"}})
    assert engine.plan()["poses"].state == "missing"
    engine.run(target="poses")
    completed = engine.completed_scene("union")
    errors = pose_errors({v.name: v.pose_matrix for v in completed.views}, truth)
    assert max(e[0] for e in errors.values()) < 0.02
    assert engine.completed_scene("poses").views[0].pose is None  # the stage itself sees the scene as given


def test_posed_scene_skips_the_stage(tmp_path):
    sim = tmp_path / "sim"
    simulate.generate_scene(sim, preset="cuboid", views=2, test_views=0, height=32, effects="none")
    plan = Engine(load_scene(sim), tmp_path / "run", build_registry()).plan()
    assert plan["poses"].state == "skipped" and plan["poses"].reason == "every view has a pose in scene.json"


def test_panoramas_sharing_no_content_are_a_clear_error(tmp_path, capsys):
    scene = tmp_path / "scene"
    (scene / "images").mkdir(parents=True)
    for seed, name in ((1, "a"), (2, "b")):  # two different rooms
        sim = tmp_path / f"room{seed}"
        simulate.generate_scene(sim, preset="cuboid", views=1, test_views=0, height=256, seed=seed,
                                effects=COLMAP_EFFECTS)
        shutil.copyfile(sim / "images" / "train_00.png", scene / "images" / f"{name}.png")
    (scene / "scene.json").write_text(json.dumps({"views": [
        {"name": "a", "image": "images/a.png"}, {"name": "b", "image": "images/b.png"}]}))
    code, out, err = invoke(["run", "poses", scene, "--out", tmp_path / "run"], capsys)
    assert code == 2
    assert "no two of the 2 panoramas share content" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "run" / "poses" / "artifact.json").exists()


def _zind_unposed(tmp_path: Path) -> tuple[Path, dict[str, np.ndarray]]:
    """A copy of zind_pair as the README's own-panoramas recipe writes a scene: names, images,
    camera heights and the nadir cap, no poses."""
    scene = tmp_path / "zind"
    shutil.copytree(ZIND, scene)
    manifest = json.loads((scene / "scene.json").read_text())
    truth = {v["name"]: np.asarray(v.pop("pose")) for v in manifest["views"]}
    manifest["nadir_mask_deg"] = 35.0  # the tripod travels with the camera
    (scene / "scene.json").write_text(json.dumps(manifest))
    return scene, truth


def _check_zind_pose(data: dict, truth: dict[str, np.ndarray]) -> None:
    posed = {v["view"]: np.asarray(v["pose"]) for v in data["views"]}
    rel = np.linalg.inv(posed["pano_12"]) @ posed["pano_18"]
    rel_true = np.linalg.inv(truth["pano_12"]) @ truth["pano_18"]
    assert rotation_angle_deg(rel[:3, :3].T @ rel_true[:3, :3]) < 1.0
    cos = rel[:3, 3] @ rel_true[:3, 3] / np.linalg.norm(rel[:3, 3]) / np.linalg.norm(rel_true[:3, 3])
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))) < 3.0
    # camera_height 1 in both: the recovered metric scale is the annotation's unit
    assert abs(np.linalg.norm(rel[:3, 3]) / np.linalg.norm(rel_true[:3, 3]) - 1.0) < 0.05


@pytest.mark.skipif(not ZIND.is_dir(), reason="shared data zind_pair absent")
def test_zind_pair_posed_by_default_within_1_degree_3_degrees_and_5_percent(tmp_path):
    # COLMAP places neither panorama; the default (auto) takes the upright solver (docs/poses.md)
    scene, truth = _zind_unposed(tmp_path)
    data = _run_poses(scene, tmp_path / "run")
    assert data["method"] == "upright" and data["requested_method"] == "auto"
    assert data["frame"] == "floor" and data["pairs"][0]["inliers"] >= 20 and data["pairs"][0]["used"]
    _check_zind_pose(data, truth)


@pytest.mark.skipif(not ZIND.is_dir(), reason="shared data zind_pair absent")
def test_colmap_failing_on_a_far_pair_suggests_the_upright_solver(tmp_path, capsys):
    scene, _ = _zind_unposed(tmp_path)
    code, out, err = invoke(["run", "poses", scene, "--out", tmp_path / "run", "--set", "poses.method=equirect"],
                            capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1  # COLMAP's own log stays off stderr
    assert "try --set poses.method=upright" in err


@pytest.mark.skipif(not ZIND.is_dir(), reason="shared data zind_pair absent")
def test_readme_recipe_on_a_copy_of_zind_pair(tmp_path, capsys, monkeypatch):
    """README "Your own panoramas (no poses)", as written, no --set: status, run poses, run all,
    report. The scene's pano-pipe.yaml keeps the training short, as a user would keep settings."""
    scene, truth = _zind_unposed(tmp_path)
    (scene / "pano-pipe.yaml").write_text("train:\n  iterations: 30\n  height: 32\n")
    monkeypatch.chdir(tmp_path)  # the default run folder runs/<scene-name>/
    code, out, err = invoke(["status", "zind"], capsys)
    assert code == 0 and err == "" and "2 of 2 views have no pose" in out
    code, out, err = invoke(["run", "poses", "zind"], capsys)
    assert code == 0 and err == "", err
    assert "poses: 2 of 2 views placed by upright" in " ".join(out.split())
    run = tmp_path / "runs" / "zind_pair"
    _check_zind_pose(json.loads((run / "poses" / "artifact.json").read_text())["data"], truth)
    code, out, err = invoke(["run", "all", "zind"], capsys)
    assert code == 0 and err == "", err
    code, out, err = invoke(["report", "zind"], capsys)
    assert code == 0 and err == "", err
    html = (run / "report" / "report.html").read_text()
    assert 'id="poses"' in html and "pair graph" in html


def test_run_all_on_names_images_and_splits_only(tmp_path, capsys):
    scene, _ = _simulated(tmp_path, 4, test_views=1)
    manifest = json.loads((scene / "scene.json").read_text())
    for v in manifest["views"]:
        v.pop("camera_height")  # the default camera height sets the scale
    (scene / "scene.json").write_text(json.dumps(manifest))
    assert all(set(v) == {"name", "image", "split"} for v in manifest["views"])
    run = tmp_path / "run"
    code, out, err = invoke(["run", "all", scene, "--out", run, "--set", "train.iterations=30",
                             "--set", "train.height=32"], capsys)
    assert code == 0, err
    assert (run / "train" / "point_cloud.ply").is_file()
    assert json.loads((run / "evaluate" / "artifact.json").read_text())["data"]
    code, out, err = invoke(["report", scene, "--out", run], capsys)
    assert code == 0, err
    assert (run / "report" / "report.html").is_file()
