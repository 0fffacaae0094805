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


def hard_case_scene(kind, dtype):
    """A few ordinary Gaussians plus the hard one(s)."""
    base_means = [dir_from_angles(a, 0.1 * i) * (1.5 + 0.3 * i) for i, a in enumerate((0.5, 2.0, -1.0, -2.5))]
    means = [m for m in base_means]
    quats = [[1.0, 0.1 * i, 0.2, -0.1] for i in range(4)]
    scales = [[0.2, 0.1, 0.15]] * 4
    ops = [0.6, 0.7, 0.8, 0.5]
    extra = {
        "north_pole": ([0.0, -2.0, 0.0], [1, 0, 0, 0], [0.3, 0.2, 0.1], 0.9),
        "south_pole": ([0.0, 2.0, 0.0], [0.3, 0.4, 0.5, 0.6], [0.3, 0.2, 0.1], 0.9),
        "seam": ([0.0, 0.0, -2.0], [1, 0, 0, 0], [0.5, 0.2, 0.1], 0.9),
        "at_camera": ([1e-6, 0.0, 0.0], [1, 0, 0, 0], [0.1, 0.1, 0.1], 0.9),
        "far": ([1e4, 0.0, 3e3], [1, 0, 0, 0], [50.0, 50.0, 50.0], 0.9),
        "far_small": ([0.0, 0.0, 1e4], [1, 0, 0, 0], [1e-3, 1e-3, 1e-3], 0.9),
        "tiny": ([0.3, 0.1, 1.0], [1, 0, 0, 0], [1e-9, 1e-9, 1e-9], 0.9),
        "huge": ([0.3, 0.1, 1.0], [1, 0, 0, 0], [1e3, 1e3, 1e3], 0.9),
        "mixed_scales": ([0.3, 0.1, 1.0], [0.7, 0.1, 0.5, 0.2], [1e3, 1e-9, 1.0], 0.9),
        "disc_face_on": ([0.0, 0.0, 1.5], [1, 0, 0, 0], [0.3, 0.3, 1e-9], 0.9),
        "disc_edge_on": ([0.0, 0.0, 1.5], [0.7071067811865476, 0.0, 0.7071067811865476, 0.0], [0.3, 0.3, 1e-9], 0.9),
        "disc_oblique": ([1.0, -0.5, 1.5], [0.9, 0.3, 0.2, 0.1], [0.3, 0.2, 1e-9], 0.9),
        "zero_quat": ([0.5, 0.0, 1.5], [0, 0, 0, 0], [0.3, 0.1, 0.1], 0.9),
        "unnormalised_quat": ([0.5, 0.0, 1.5], [20.0, 3.0, -5.0, 1.0], [0.3, 0.1, 0.1], 0.9),
        "tiny_quat": ([0.5, 0.0, 1.5], [1e-30, 0, 1e-30, 0], [0.3, 0.1, 0.1], 0.9),
        "opacity_zero": ([0.0, 0.0, 1.5], [1, 0, 0, 0], [0.3, 0.3, 0.3], 0.0),
        "opacity_one": ((dir_from_angles(math.pi / 32, -math.pi / 32) * 1.5).tolist(), [1, 0, 0, 0], [0.3, 0.3, 0.3], 1.0),
        "beyond_hemisphere": ([0.0, 0.0, 0.1], [1, 0, 0, 0], [2.0, 2.0, 2.0], 0.9),
        "just_past_near": ([0.0, 0.0, 0.0501], [1, 0, 0, 0], [0.01, 0.01, 0.01], 0.9),
        "behind_pinhole": ([0.0, 0.0, -1.0], [1, 0, 0, 0], [0.3, 0.3, 0.3], 0.9),
    }[kind]
    means.append(torch.tensor(extra[0], dtype=torch.float64))
    quats.append(extra[1])
    scales.append(extra[2])
    ops.append(extra[3])
    n = len(means)
    t = lambda x: torch.tensor(x, dtype=dtype)
    return [
        torch.stack(means).to(dtype), t(quats), t(scales), t(ops),
        torch.rand(n, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64).to(dtype),
    ]


HARD_KINDS = ["north_pole", "south_pole", "seam", "at_camera", "far", "far_small", "tiny", "huge", "mixed_scales",
              "disc_face_on", "disc_edge_on", "disc_oblique", "zero_quat", "unnormalised_quat", "tiny_quat",
              "opacity_zero", "opacity_one", "beyond_hemisphere", "just_past_near"]


def equal_distance_cluster(seed, phi=math.pi, n=10, radius=2.0, dtype=torch.float32):
    """issue 35's case: n Gaussians at exactly ``radius`` from the camera (the same distance to
    the last bit of their true value), spread ±0.2 rad about longitude ``phi`` (π: straddling
    the ±180° seam) and ±1 rad in latitude. Which one is in front is a tie that every backend
    must break alike (splatting.project.depth_key)."""
    import numpy as np

    rng = np.random.default_rng(seed)
    lon = phi + rng.uniform(-0.2, 0.2, n)
    lat = rng.uniform(-1, 1, n)
    means = np.stack([np.cos(lat) * np.sin(lon), -np.sin(lat), np.cos(lat) * np.cos(lon)], 1) * radius
    quats = rng.normal(size=(n, 4))
    scales = np.exp(rng.uniform(np.log(0.05), np.log(0.4), (n, 3)))
    ops = rng.uniform(0.2, 0.95, n)
    cols = rng.uniform(0, 1, (n, 3))
    return [torch.tensor(a, dtype=dtype) for a in (means, quats, scales, ops, cols)]
