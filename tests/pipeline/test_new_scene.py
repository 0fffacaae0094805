"""`pano-pipe new SCENE PANORAMA...`: a scene folder from panoramas, whole or not at all."""

from __future__ import annotations

import json
import os

import cv2
import numpy as np
import pytest

from pipeline.settings import REAL_CAPTURE_SETTINGS, SCENE_CONFIG, make_engine
from schemas.scene_loader import load_scene
from tests.clitools import invoke


def _pano(path, h=32, w=64, seed=0):
    cv2.imwrite(str(path), np.random.default_rng(seed).integers(0, 255, (h, w, 3), dtype=np.uint8))
    return path


@pytest.fixture()
def photos(tmp_path):
    d = tmp_path / "photos"
    d.mkdir()
    return [_pano(d / f"{n}.png", seed=i) for i, n in enumerate(["kitchen", "hall 2", "kitchen-b", "den"])]


def test_new_writes_a_loadable_scene_and_prints_the_next_command(tmp_path, photos, capsys):
    out = tmp_path / "scene"
    code, stdout, err = invoke(["new", out, *photos, "--test-every", "2", "--camera-height", "1.5"], capsys)
    assert code == 0, err
    manifest = json.loads((out / "scene.json").read_text())
    views = manifest["views"]
    assert [v["name"] for v in views] == ["kitchen", "hall 2", "kitchen-b", "den"]
    assert [v["split"] for v in views] == ["train", "test", "train", "test"]
    assert all(v["camera_height"] == 1.5 and "pose" not in v for v in views)
    assert manifest["nadir_mask_deg"] == 35 and manifest["name"] == "scene"
    for src, v in zip(photos, views):
        copy = out / v["image"]
        assert copy.read_bytes() == src.read_bytes() and not os.path.samefile(copy, src)
    assert len(load_scene(out).views) == 4
    assert f"pano-pipe run all {out}" in stdout


def test_new_links_with_link_and_takes_nadir_and_default_split(tmp_path, photos, capsys):
    out = tmp_path / "scene"
    code, _, err = invoke(["new", out, *photos, "--link", "--nadir-mask-deg", "0"], capsys)
    assert code == 0, err
    manifest = json.loads((out / "scene.json").read_text())
    assert manifest.get("nadir_mask_deg", 0) == 0
    assert all(v["split"] == "train" for v in manifest["views"])  # 4 views, every 8th held out: none
    assert all(os.path.samefile(out / v["image"], src) for src, v in zip(photos, manifest["views"]))


def test_new_starts_the_scene_with_the_settings_for_captured_panoramas(tmp_path, photos, capsys):
    out = tmp_path / "scene"
    code, stdout, err = invoke(["new", out, *photos], capsys)
    assert code == 0, err
    assert SCENE_CONFIG in stdout and "pano-pipe new" in (out / SCENE_CONFIG).read_text()
    engine = make_engine(out, tmp_path / "run", None, None)
    for stage, params in REAL_CAPTURE_SETTINGS.items():
        got, defaults = engine.params_for(stage), type(engine.params_for(stage))()
        for param, (value, _) in params.items():
            assert getattr(got, param) == value != getattr(defaults, param), (stage, param)
    # below --set, as any scene's own settings
    engine = make_engine(out, tmp_path / "run", None, ["train.random_turn_interp=bicubic"])
    assert engine.params_for("train").random_turn_interp == "bicubic" and engine.params_for("train").appearance


def test_new_makes_clashing_file_names_unique(tmp_path, capsys):
    a = _pano(tmp_path / "room.png")
    b = _pano(tmp_path / "room.jpg", seed=1)
    code, _, err = invoke(["new", tmp_path / "scene", a, b], capsys)
    assert code == 0, err
    assert [v.name for v in load_scene(tmp_path / "scene").views] == ["room", "room_2"]


def _bad_inputs(tmp_path, photos):
    not_2to1 = _pano(tmp_path / "photos" / "square.png", h=32, w=32)
    taken = tmp_path / "taken"
    taken.mkdir()
    (taken / "notes.txt").write_text("mine")
    return {
        "not 2:1": ([*photos, not_2to1], tmp_path / "scene", not_2to1),
        "missing": ([photos[0], tmp_path / "photos" / "nope.jpg"], tmp_path / "scene", tmp_path / "photos" / "nope.jpg"),
        "non-empty scene folder": (photos, taken, taken),
    }


@pytest.mark.parametrize("case", ["not 2:1", "missing", "non-empty scene folder"])
def test_bad_input_is_one_line_naming_the_file_and_writes_nothing(tmp_path, photos, capsys, case):
    panoramas, out, named = _bad_inputs(tmp_path, photos)[case]
    before = sorted(p.name for p in tmp_path.iterdir())
    code, _, err = invoke(["new", out, *panoramas], capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert named.name in err
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # no scene, no temporary folder
    if case == "non-empty scene folder":
        assert [p.name for p in out.iterdir()] == ["notes.txt"]


def test_one_panorama_is_the_world_frame_and_runs_without_the_poses_stage(tmp_path, photos, capsys):
    """A single panorama has nothing to be placed against: `new` gives it the identity pose (the poses
    stage would refuse one panorama), so `run all` can go from it with a supplied layout."""
    out = tmp_path / "one"
    code, stdout, err = invoke(["new", out, photos[0], "--camera-height", "1.5"], capsys)
    assert code == 0, err
    (view,) = json.loads((out / "scene.json").read_text())["views"]
    assert view["pose"] == np.eye(4).tolist() and view["split"] == "train"
    assert "world frame" in stdout
    scene = load_scene(out)
    assert not scene.manifest.unposed_views()
    from stages import poses

    assert poses.skip_reason(scene, poses.Params()) == "every view has a pose in scene.json"
    # several panoramas still get no pose: the poses stage recovers them
    code, _, err = invoke(["new", tmp_path / "two", *photos[:2]], capsys)
    assert code == 0, err
    assert all("pose" not in v for v in json.loads((tmp_path / "two" / "scene.json").read_text())["views"])
