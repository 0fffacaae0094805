"""nerfstudio transforms.json import: poses and pixel directions agree with DESIGN.md."""

from __future__ import annotations

import json

import numpy as np
import pytest

from panogeom import angles_to_dirs
from pipeline.errors import PanoError
from pipeline.importers import import_nerfstudio, nerfstudio_to_pose, pose_to_nerfstudio
from pipeline.scene_loader import load_scene


def nerfstudio_direction(x_ndc: float, y_ndc: float) -> np.ndarray:
    """nerfstudio's equirectangular ray in its camera frame (OpenGL axes).

    x_ndc in [-1, 1] left to right, y_ndc in [-1/2, 1/2] bottom to top.
    """
    theta = -np.pi * x_ndc
    phi = np.pi * (0.5 - y_ndc)
    return np.array([-np.sin(theta) * np.sin(phi), np.cos(phi), -np.cos(theta) * np.sin(phi)])


@pytest.mark.parametrize("world_up", ["+z", "+y", "-y"])
def test_pose_round_trip(world_up):
    rng = np.random.default_rng(1)
    from scipy.spatial.transform import Rotation

    pose = np.eye(4)
    pose[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    pose[:3, 3] = rng.normal(size=3)
    back = nerfstudio_to_pose(pose_to_nerfstudio(pose, world_up), world_up)
    np.testing.assert_allclose(back, pose, atol=1e-12)


def test_pixel_directions_match_in_world():
    rng = np.random.default_rng(2)
    from scipy.spatial.transform import Rotation

    c2w_gl = np.eye(4)
    c2w_gl[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    ours = nerfstudio_to_pose(c2w_gl, "+z")
    world = {"+z": np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]])}["+z"]
    for u, v in [(0.5, 0.5), (0.1, 0.3), (0.9, 0.8), (0.25, 0.5)]:  # image fractions, v down
        d_ns = c2w_gl[:3, :3] @ nerfstudio_direction(2 * u - 1, 0.5 - v)
        phi, theta = (u - 0.5) * 2 * np.pi, (0.5 - v) * np.pi
        d_ours = ours[:3, :3] @ angles_to_dirs(phi, theta)
        np.testing.assert_allclose(d_ours, world @ d_ns, atol=1e-12)


def test_import_writes_valid_scene(tiny_scene, tmp_path):
    manifest = json.loads((tiny_scene / "scene.json").read_text())
    frames = [
        {"file_path": f"../tiny/{v['image']}", "transform_matrix": pose_to_nerfstudio(v["pose"]).tolist()}
        for v in manifest["views"]
    ]
    ns = tmp_path / "ns"
    ns.mkdir()
    (ns / "transforms.json").write_text(json.dumps({"camera_model": "EQUIRECTANGULAR", "frames": frames}))
    import_nerfstudio(ns / "transforms.json", tmp_path / "imported", test_every=3)
    scene = load_scene(tmp_path / "imported")
    assert [v.split for v in scene.views] == ["train", "train", "test"]
    for got, want in zip(scene.views, manifest["views"]):
        np.testing.assert_allclose(got.pose_matrix, want["pose"], atol=1e-12)


def test_import_errors(tmp_path):
    with pytest.raises(PanoError, match="file does not exist"):
        import_nerfstudio(tmp_path / "missing.json", tmp_path / "out")
    (tmp_path / "t.json").write_text(json.dumps({"frames": [{"file_path": "x.png", "transform_matrix": []}]}))
    with pytest.raises(PanoError, match=r"x.png: image missing \(named by frames.0.file_path\)"):
        import_nerfstudio(tmp_path / "t.json", tmp_path / "out")
