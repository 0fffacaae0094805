"""The y-up conversion: an exact involution that every render agrees with."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from export_helpers import random_gaussians

import splatting
from export.transform import to_y_up, y_up_points, y_up_pose
from gaussians.model import render


def test_y_up_twice_is_identity(model):
    twice = to_y_up(to_y_up(model))
    for name, t in model.tensors().items():
        assert torch.equal(getattr(twice, name), t), name


def test_y_up_moves_points_and_keeps_handedness(model):
    up = to_y_up(model)
    np.testing.assert_array_equal(up.means.numpy(), y_up_points(model.means.numpy()))
    assert float(np.linalg.det(y_up_pose(np.eye(4))[:3, :3])) == pytest.approx(1.0)


def _pose(yaw: float, pitch: float, t) -> np.ndarray:
    cy, sy, cp, sp = math.cos(yaw), math.sin(yaw), math.cos(pitch), math.sin(pitch)
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rx = np.array([[1, 0, 0], [0, cp, -sp], [0, sp, cp]])
    m = np.eye(4)
    m[:3, :3] = ry @ rx
    m[:3, 3] = t
    return m


@pytest.mark.parametrize("camera", ["equirect", "pinhole"])
def test_y_up_renders_the_same_images(camera):
    # degree 3 with strong SH: a wrong sign on any band shows up in the image
    g = random_gaussians(120, degree=3, seed=3, dtype=torch.float64, spread=1.5)
    g.sh_rest = g.sh_rest * 2.0
    g.log_scales = g.log_scales.clamp(max=math.log(0.15))
    cam = (splatting.EquirectCamera(16, 32) if camera == "equirect"
           else splatting.PinholeCamera(20.0, 20.0, 16.0, 12.0, 32, 24))
    c2w = _pose(0.7, -0.3, [0.2, -0.1, -2.5])
    up = to_y_up(g)
    a = render(g, torch.as_tensor(np.linalg.inv(c2w)), cam, background=[0.1, 0.2, 0.3])
    b = render(up, torch.as_tensor(np.linalg.inv(y_up_pose(c2w))), cam, background=[0.1, 0.2, 0.3])
    assert float(a.alpha.max()) > 0.3  # the camera sees the Gaussians
    torch.testing.assert_close(b.image, a.image, atol=1e-7, rtol=1e-6)
    torch.testing.assert_close(b.depth, a.depth, atol=1e-7, rtol=1e-6)
    # and the conversion is not a no-op: the y-up model from the old pose looks different
    c = render(up, torch.as_tensor(np.linalg.inv(c2w)), cam, background=[0.1, 0.2, 0.3])
    assert float((c.image - a.image).abs().max()) > 0.05
