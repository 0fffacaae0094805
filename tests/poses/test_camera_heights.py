"""Camera heights flow from the poses stage to the stages after it (issue 36, item 3): the
heights the poses were made metric with are recorded per view and fill in the views that
scene.json leaves without one, so the layout stage no longer assumes 1.6 m beside them."""

from __future__ import annotations

import json

import numpy as np

from pipeline.registry import build_registry
from runtime.stage import Loaded
from schemas.poses import PosesOutput, ViewPose
from schemas.scene_loader import load_scene
from sfm.frame import align_to_floor


def _level_cameras(heights_sfm: list[float], floor_y: float = 2.0):
    """Cameras (SfM frame, y down) at `floor_y − h` above a textured floor plane y = floor_y."""
    cams = {}
    for i, h in enumerate(heights_sfm):
        m = np.eye(4)
        m[:3, 3] = [1.5 * i, floor_y - h, 0.7 * i]
        cams[f"v{i}"] = m
    rng = np.random.default_rng(0)
    floor = np.column_stack([rng.uniform(-4, 7, 4000), np.full(4000, floor_y) + rng.normal(0, 1e-4, 4000),
                             rng.uniform(-4, 5, 4000)])
    return cams, floor


def test_the_floor_fit_measures_every_cameras_height():
    cams, floor = _level_cameras([0.8, 0.8, 0.8])  # SfM units; 1.5 m given for one: 1.875 m per unit
    fit = align_to_floor(cams, floor, {"v0": 1.5, "v1": 1.5, "v2": 1.5}, ["v0", "v1", "v2"])
    assert fit.source == "floor" and set(fit.camera_heights) == {"v0", "v1", "v2"}
    assert np.allclose(list(fit.camera_heights.values()), 1.5, atol=1e-3)


def test_recovered_heights_fill_only_the_views_without_one(tiny_scene, tmp_path):
    root = tiny_scene  # v0, v1 train, v2 test
    manifest = json.loads((root / "scene.json").read_text())
    for v in manifest["views"]:
        v["pose"] = None
    manifest["views"][0]["camera_height"] = 1.43  # the README's recipe: one view's height
    for v in manifest["views"][1:]:
        v.pop("camera_height")
    (root / "scene.json").write_text(json.dumps(manifest))
    scene = load_scene(root)
    pose = np.eye(4).tolist()
    data = PosesOutput.model_validate({
        "method": "upright", "working_height": 8, "frame": "floor", "scale": 1.0, "scale_uncertainty": 0.0,
        "points": 0, "mean_track_length": 0.0, "verified_pairs": 2, "sparse_points": "points.ply",
        "drawing": "cameras.png",
        "views": [ViewPose(view=f"v{i}", registered=True, pose=pose, camera_height=1.431).model_dump()
                  for i in range(3)]})
    complete = build_registry()["poses"].completes_scene
    done = complete(scene, Loaded(data, tmp_path))
    assert [v.camera_height for v in done.views] == [1.43, 1.431, 1.431]  # the given one is kept
    assert all(v.pose is not None for v in done.views)


def test_layout_runs_on_the_scene_the_poses_completed():
    """The layout stage is downstream of poses (an optional input), so it sees the completed scene."""
    registry = build_registry()
    assert registry["layout"].inputs.get("poses") is False
