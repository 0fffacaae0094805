"""Hard cases: every output and every gradient stays finite (both backends, both dtypes)."""

import math

import pytest
import torch

import splatting
from splat_helpers import BACKENDS, all_finite, dir_from_angles, eye

DTYPES = [torch.float32, torch.float64]


def _scene(kind, dtype):
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


KINDS = ["north_pole", "south_pole", "seam", "at_camera", "far", "far_small", "tiny", "huge", "mixed_scales",
         "disc_face_on", "disc_edge_on", "disc_oblique", "zero_quat", "unnormalised_quat", "tiny_quat",
         "opacity_zero", "opacity_one", "beyond_hemisphere", "just_past_near"]


def _check(kind, backend, dtype, camera, eps2d=0.3):
    params = [p.clone().requires_grad_(True) for p in _scene(kind, dtype)]
    out = splatting.render(*params, eye(dtype), camera, backend=backend, eps2d=eps2d,
                           background=torch.tensor([0.1, 0.2, 0.3], dtype=dtype))
    assert all_finite(out.image, out.alpha, out.depth, out.means2d)
    assert float(out.alpha.detach().min()) >= 0 and float(out.alpha.detach().max()) <= 1
    target = torch.rand(out.image.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64).to(dtype)
    loss = ((out.image - target) ** 2).sum() + 0.1 * out.depth.sum() + out.alpha.sum()
    loss.backward()
    for p in params:
        assert p.grad is not None and all_finite(p.grad), kind
    assert out.means2d.grad is not None and all_finite(out.means2d.grad)
    return out, params


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("kind", KINDS)
def test_hard_case_equirect(kind, backend, dtype):
    out, params = _check(kind, backend, dtype, splatting.EquirectCamera(16, 32))
    vis = out.visible
    if kind in ("at_camera", "opacity_zero"):
        assert not bool(vis[-1]) and int(out.radii[-1]) == 0
        assert float(params[0].grad[-1].abs().max()) == 0.0
    if kind in ("north_pole", "south_pole", "seam", "tiny", "huge", "disc_face_on", "opacity_one",
                "beyond_hemisphere", "zero_quat", "unnormalised_quat"):
        assert bool(vis[-1])
    if kind == "opacity_one":
        lone = splatting.render(*[p[-1:].detach() for p in params], eye(dtype), splatting.EquirectCamera(16, 32), backend=backend)
        assert float(lone.alpha.max()) == pytest.approx(0.99, abs=1e-6)  # the clamp
        assert float(lone.alpha[8, 16]) == pytest.approx(0.99, abs=1e-6)
    if kind == "beyond_hemisphere":
        # renders only where the pixel direction is in front of its tangent plane
        dirs = splatting.EquirectCamera(16, 32).pixel_dirs(dtype)
        behind = dirs[..., 2] <= 0
        lone = splatting.render(*[p[-1:].detach() for p in params], eye(dtype), splatting.EquirectCamera(16, 32), backend=backend)
        assert float(lone.alpha[behind].max()) == 0.0 and float(lone.alpha[~behind].max()) > 0.5


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("kind", ["disc_edge_on", "tiny", "far_small", "mixed_scales"])
def test_hard_case_without_dilation(kind, backend):
    _check(kind, backend, torch.float32, splatting.EquirectCamera(16, 32), eps2d=0.0)
    _check(kind, backend, torch.float64, splatting.EquirectCamera(16, 32), eps2d=0.0)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("kind", ["behind_pinhole", "at_camera", "huge", "disc_edge_on", "zero_quat", "opacity_one", "far"])
def test_hard_case_pinhole(kind, backend):
    cam = splatting.PinholeCamera(12.0, 12.0, 10.0, 8.0, 20, 16)
    out, _ = _check(kind, backend, torch.float32, cam)
    if kind in ("behind_pinhole", "at_camera"):
        assert not bool(out.visible[-1])


def test_zero_quaternion_is_identity():
    a = _scene("zero_quat", torch.float64)
    b = [x.clone() for x in a]
    b[1][-1] = torch.tensor([1.0, 0, 0, 0], dtype=torch.float64)
    cam = splatting.EquirectCamera(16, 32)
    torch.testing.assert_close(splatting.render(*a, eye(), cam).image, splatting.render(*b, eye(), cam).image)
    c = [x.clone() for x in a]
    c[1][-1] = torch.tensor([0.5, 0.1, -0.2, 0.3], dtype=torch.float64)
    d = [x.clone() for x in c]
    d[1][-1] = d[1][-1] * 37.0
    torch.testing.assert_close(splatting.render(*c, eye(), cam).image, splatting.render(*d, eye(), cam).image)
