"""Helpers for the splatting tests (imported by the test files of this folder)."""

from __future__ import annotations

import math

import torch

from splatting.project import project
from splatting.reference import rasterize_dense
from splatting.render import _color_fn

BACKENDS = ("torch", "cpp")


def random_scene(n, seed=0, dtype=torch.float64, spread=2.0, scale=(0.05, 0.35), opacity=(0.05, 0.95)):
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=torch.float64) * spread
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    scales = torch.rand(n, 3, generator=g, dtype=torch.float64) * (scale[1] - scale[0]) + scale[0]
    op = torch.rand(n, generator=g, dtype=torch.float64) * (opacity[1] - opacity[0]) + opacity[0]
    col = torch.rand(n, 3, generator=g, dtype=torch.float64)
    return [x.to(dtype) for x in (means, quats, scales, op, col)]


def eye(dtype=torch.float64):
    return torch.eye(4, dtype=dtype)


def dir_from_angles(phi, theta, dtype=torch.float64):
    return torch.tensor([math.cos(theta) * math.sin(phi), -math.sin(theta), math.cos(theta) * math.cos(phi)], dtype=dtype)


def yaw_matrix(a, dtype=torch.float64):
    """Rotation about the vertical (y) axis taking phi to phi + a."""
    c, s = math.cos(a), math.sin(a)
    m = torch.eye(4, dtype=dtype)
    m[:3, :3] = torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]], dtype=dtype)
    return m


def dense_render(means, quats, scales, op, col, viewmat, camera, eps2d=0.3, near=0.05):
    """Every pixel against every Gaussian, no tiles / boxes, plain autograd."""
    pr = project(means, quats, scales, op, _color_fn(col, None, means.shape[0]), viewmat, camera, eps2d, near)
    dirs = camera.pixel_dirs(dtype=means.dtype)
    color, depth, alpha = rasterize_dense(pr.packed, dirs)
    return color, depth, alpha


def all_finite(*ts):
    return all(bool(torch.isfinite(t).all()) for t in ts if t is not None)
