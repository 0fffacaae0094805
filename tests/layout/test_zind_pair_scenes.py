"""scripts/zind_pair_scenes.py on the real pair (skips when ../shared/data/zind_pair is absent): the
dataset-to-world mapping agrees with the pair's scene.json, and the supplied layout it writes is one
the pipeline reads and that holds the held-out camera inside the room."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from layoutnet.formats import read_layout
from schemas.scene_loader import load_scene
from tests.scripttools import load_script

REPO = Path(__file__).resolve().parents[2]
ZIND = REPO.parent / "shared" / "data" / "zind_pair"
pytestmark = pytest.mark.skipif(not (ZIND / "scene.json").is_file(), reason="shared zind_pair data absent")


def _script():
    return load_script("zind_pair_scenes")


def test_dataset_frame_maps_pano2_onto_its_pose():
    """pano_12's annotated position (dataset frame) lands on its camera centre in scene.json."""
    script = _script()
    annotation = json.loads((ZIND / "relative_pose_annotation.json").read_text())
    views = {v["name"]: v for v in json.loads((ZIND / "scene.json").read_text())["views"]}
    xz = script.dataset_to_world(np.asarray(annotation["pano2_coordinates_relative_to_pano1"], dtype=float))
    centre = np.asarray(views["pano_12"]["pose"])[:3, 3]
    np.testing.assert_allclose(xz[0], centre[[0, 2]], atol=1e-6)
    np.testing.assert_allclose(np.asarray(views["pano_18"]["pose"])[:3, 3], 0.0)


def test_supplied_layout_holds_the_held_out_camera(tmp_path):
    """Each direction's scene loads with its layout; the training view's floor boundary, looking
    towards the held-out camera (3.59 camera heights away), reaches a wall beyond it."""
    script = _script()
    for name, train, test in (("zind_a", "pano_18", "pano_12"), ("zind_b", "pano_12", "pano_18")):
        script.make_scene(tmp_path, name, 35.0, with_layout=True)
        scene = load_scene(tmp_path / name)
        splits = {v.name: v.split for v in scene.views}
        assert splits == {train: "train", test: "test"}
        bounds = read_layout(tmp_path / name / "layout" / f"{train}.npy").boundaries
        assert bounds.shape == (2, 1024) and bounds[0].min() > 0 > bounds[1].max()
        poses = {v.name: np.asarray(v.pose) for v in scene.views}
        offset = np.linalg.inv(poses[train]) @ poses[test][:, 3]  # held-out centre in the camera frame
        phi = np.arctan2(offset[0], offset[2])
        column = int((phi / (2 * np.pi) + 0.5) * 1024)
        floor_distance = 1.0 / np.tan(-bounds[1, column])  # camera height 1
        assert floor_distance > np.hypot(offset[0], offset[2]) > 3.5
        assert (tmp_path / name / "layout_overlay" / f"{train}.png").is_file()
