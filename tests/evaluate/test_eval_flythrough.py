"""Fly-through path interpolation and video writing."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from evaluation.flythrough import interpolate_poses, path_views, render_flythrough, write_video
from evaluation.model_io import equirect_camera, pinhole_camera
from runfs.errors import PanoError


def _pose(yaw_deg, pos):
    m = np.eye(4)
    m[:3, :3] = Rotation.from_euler("y", yaw_deg, degrees=True).as_matrix()
    m[:3, 3] = pos
    return m


def test_interpolation_hits_keys_and_slerps():
    a, b, c = _pose(0, [0, -1.5, 0]), _pose(90, [2, -1.5, 0]), _pose(90, [2, -1.5, 2])
    out = interpolate_poses([a, b, c], 41)
    assert out.shape == (41, 4, 4)
    np.testing.assert_allclose(out[0], a, atol=1e-12)
    np.testing.assert_allclose(out[-1], c, atol=1e-12)
    for m in out:  # rigid
        np.testing.assert_allclose(m[:3, :3].T @ m[:3, :3], np.eye(3), atol=1e-9)
        assert m[3].tolist() == [0, 0, 0, 1]
    # segment lengths: a->b 2 m + 0.5·(π/2) rad-metres, b->c 2 m: b sits at that share of the path
    share = (2 + 0.25 * math.pi) / (4 + 0.25 * math.pi)
    s = np.linspace(0, 1, 41)
    k = int(np.argmin(np.abs(s - share / 2)))  # halfway along the first segment
    yaw = Rotation.from_matrix(out[k, :3, :3]).as_euler("yxz", degrees=True)[0]
    assert yaw == pytest.approx(90 * s[k] / share, abs=1e-6)
    assert out[k, 0, 3] == pytest.approx(2 * s[k] / share, abs=1e-9)
    # steady pace: position steps on the straight second segment are equal
    steps = np.linalg.norm(np.diff(out[s > share + 0.03, :3, 3], axis=0), axis=1)
    np.testing.assert_allclose(steps, steps[0], rtol=1e-6)


def test_single_view_spins_and_repeated_keys_are_fine():
    p = _pose(30, [1, -1.2, 0.5])
    spin = interpolate_poses([p], 8)
    np.testing.assert_allclose(spin[:, :3, 3], np.tile(p[:3, 3], (8, 1)))
    yaws = Rotation.from_matrix(spin[:, :3, :3]).as_euler("yxz", degrees=True)[:, 0]
    np.testing.assert_allclose(np.diff(np.unwrap(np.radians(yaws))), 2 * math.pi / 8, atol=1e-9)
    same = interpolate_poses([p, p, _pose(30, [2, -1.2, 0.5])], 5)
    assert np.all(np.isfinite(same))
    with pytest.raises(ValueError):
        interpolate_poses(np.zeros((2, 3, 3)), 4)


def test_path_views(sim_scene):
    assert [v.name for v in path_views(sim_scene, "train")] == ["train_00", "train_01"]
    assert [v.name for v in path_views(sim_scene, "test_00,train_01")] == ["test_00", "train_01"]
    with pytest.raises(PanoError, match="lacks"):
        path_views(sim_scene, "nope")


def test_video_round_trip(tmp_path, sim_model, sim_scene):
    frames = [np.full((16, 32, 3), i / 10) for i in range(6)]
    n = write_video(frames, tmp_path / "v.mp4", fps=12)
    cap = cv2.VideoCapture(str(tmp_path / "v.mp4"))
    assert n == 6 and cap.get(cv2.CAP_PROP_FRAME_COUNT) == 6
    assert (cap.get(cv2.CAP_PROP_FRAME_WIDTH), cap.get(cv2.CAP_PROP_FRAME_HEIGHT)) == (32, 16)
    # a short perspective and panoramic fly-through of the model
    poses = interpolate_poses([v.pose_matrix for v in path_views(sim_scene, "train")], 4)
    for cam in (pinhole_camera(24, 32), equirect_camera(16, 32)):
        r = render_flythrough(sim_model, poses, cam, tmp_path / f"{cam.kind}.mp4", fps=8)
        cap = cv2.VideoCapture(str(r.path))
        ok, frame = cap.read()
        assert ok and r.frames == 4 and frame.shape[:2] == r.size
        assert frame.std() > 5  # the room shows, not a blank frame
