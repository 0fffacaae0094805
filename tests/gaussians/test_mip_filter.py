"""Mip-Splatting's 3D smoothing filter (gaussians/mip_filter.py) against hand-computed values."""

from __future__ import annotations

import math

import pytest
import torch

import splatting
from gaussians.mip_filter import (DEFAULT_VARIANCE, filter_variance, filtered, filtered_opacity_logits,
                                  sampling_rate)
from gaussians.model import Gaussians


def _one(scales, opacity_logit, at=(0.0, 0.0, 2.0), dtype=torch.float64) -> Gaussians:
    g = Gaussians.create(torch.tensor([at], dtype=dtype), sh_degree=0,
                         log_scales=torch.log(torch.tensor([scales], dtype=dtype)), dtype=dtype)
    g.opacity_logits = torch.tensor([opacity_logit], dtype=dtype)
    return g


def test_equirect_rate_and_filter_by_hand():
    """A Gaussian 2 m from a 128×256 panorama's centre: one pixel is 2π/256 rad, so ν = 256 / (2π · 2)
    = 20.3718 px/m and the low-pass variance 0.2 / ν² = 4.81914e-4 m² (σ = 2.195 cm). Scales
    (1 mm, 1 cm, 10 cm) become sqrt(s² + v); the opacity 0.5 scales by Π s / sqrt(s² + v)."""
    g = _one([0.001, 0.01, 0.1], 0.0, at=(0.0, 1.2, 1.6))  # |(0, 1.2, 1.6)| = 2
    rate = sampling_rate(g.means, [torch.eye(4, dtype=torch.float64)], [splatting.EquirectCamera(128, 256)])
    assert rate.item() == pytest.approx(20.371832715762604, rel=1e-12)
    var = filter_variance(rate, DEFAULT_VARIANCE)
    assert var.item() == pytest.approx(4.81914e-4, rel=1e-5)
    f = filtered(g, var)
    # sqrt(1e-6 + 4.81914e-4) = 0.0219753, sqrt(1e-4 + 4.81914e-4) = 0.0241229, sqrt(1e-2 + 4.81914e-4) = 0.1023812
    assert torch.allclose(f.scales[0], torch.tensor([0.0219753, 0.0241229, 0.1023812], dtype=torch.float64),
                          rtol=1e-5)
    # sqrt(det ratio) = (1e-3 · 1e-2 · 1e-1) / (0.0219753 · 0.0241229 · 0.1023812) = 0.0184253
    assert f.opacities.item() == pytest.approx(0.5 * 0.0184253, rel=1e-5)
    # the low-pass keeps each Gaussian's integral α · sqrt(det Σ)
    assert (f.opacities * f.scales.prod(1)).item() == pytest.approx((g.opacities * g.scales.prod(1)).item(),
                                                                     rel=1e-12)


def test_rate_takes_the_finest_camera_and_pinhole_visibility():
    """Two panoramas 1 m and 3 m from a point: the nearer one's rate. A pinhole camera (fx 100) sees a
    point 4 m in front (rate 100 / 4 = 25, its depth, not its distance) but not one behind it; a point
    no camera sees gets the smallest rate of those seen."""
    eq = splatting.EquirectCamera(64, 128)
    far = torch.eye(4, dtype=torch.float64)
    far[:3, 3] = torch.tensor([-3.0, 0.0, 0.0])  # centre at x = 3
    near = torch.eye(4, dtype=torch.float64)
    near[:3, 3] = torch.tensor([1.0, 0.0, 0.0])  # centre at x = -1
    pt = torch.zeros(1, 3, dtype=torch.float64)
    assert sampling_rate(pt, [far, near], [eq, eq]).item() == pytest.approx(128 / (2 * math.pi) / 1.0)
    pin = splatting.PinholeCamera(fx=100.0, fy=100.0, cx=50.0, cy=50.0, width=100, height=100)
    pts = torch.tensor([[0.5, 0.0, 4.0], [0.0, 0.0, 8.0], [0.0, 0.0, -4.0]], dtype=torch.float64)
    r = sampling_rate(pts, [torch.eye(4, dtype=torch.float64)], [pin])
    assert r.tolist() == pytest.approx([25.0, 12.5, 12.5])


def test_filter_is_a_no_op_as_the_variance_vanishes():
    g = _one([0.001, 0.02, 0.3], 1.5)
    rate = torch.tensor([20.0], dtype=torch.float64)
    for v, tol in ((1e-14, 1e-6), (0.0, 0.0)):
        f = filtered(g, filter_variance(rate, v) if v else torch.zeros(1, dtype=torch.float64))
        assert torch.allclose(f.log_scales, g.log_scales, atol=tol, rtol=0)
        assert torch.allclose(f.opacity_logits, g.opacity_logits, atol=tol, rtol=0)
    # a much larger variance than every scale: the filtered Gaussian is the low-pass, nearly transparent
    f = filtered(g, torch.tensor([1.0], dtype=torch.float64))
    assert torch.allclose(f.scales, torch.ones(1, 3, dtype=torch.float64), atol=0.05)
    assert f.opacities.item() < 1e-4


def test_opacity_logit_is_exact_where_alpha_rounds_to_one_and_gradients_flow():
    """logit(α · r) for α = sigmoid(30) (1 in float32) stays finite and matches the float64 value."""
    o = torch.tensor([30.0, -5.0, 0.0], requires_grad=True)
    ls = torch.log(torch.tensor([[0.01] * 3, [0.01] * 3, [0.01] * 3])).requires_grad_(True)
    new = torch.log(torch.tensor([[0.0101] * 3, [0.02] * 3, [0.01] * 3]))
    out = filtered_opacity_logits(o, ls, new)
    o64, r64 = o.detach().double(), (0.01 / torch.tensor([0.0101, 0.02, 0.01], dtype=torch.float64)) ** 3
    ref = torch.logit(torch.sigmoid(o64) * r64)
    assert torch.isfinite(out).all()
    assert torch.allclose(out.double(), ref, rtol=1e-4, atol=1e-4)
    assert out[2].item() == pytest.approx(0.0, abs=1e-6)  # r = 1: unchanged
    out.sum().backward()
    assert torch.isfinite(o.grad).all() and torch.isfinite(ls.grad).all() and ls.grad.abs().sum() > 0


def test_widen_only_keeps_the_opacity():
    g = _one([0.001, 0.01, 0.1], 0.7)
    f = filtered(g, torch.tensor([1e-4], dtype=torch.float64), keep_integral=False)
    assert torch.equal(f.opacity_logits, g.opacity_logits)
    assert torch.allclose(f.scales, torch.sqrt(g.scales ** 2 + 1e-4))


def test_reset_cap_clamps_the_filtered_opacity():
    """After the reset the opacity as drawn is min(drawn, 0.01): a wide Gaussian (r ≈ 1) is capped
    near 0.01 raw, a thin one (r = 0.0184, drawn 0.0092 < 0.01) keeps its raw opacity."""
    from gaussians.mip_filter import reset_cap_logits

    ls = torch.log(torch.tensor([[0.001, 0.01, 0.1], [0.5, 0.5, 0.5]], dtype=torch.float64))
    var = torch.full((2,), 4.81914e-4, dtype=torch.float64)
    o = torch.tensor([0.0, 3.0], dtype=torch.float64)
    g = Gaussians.create(torch.zeros(2, 3, dtype=torch.float64), sh_degree=0, log_scales=ls, dtype=torch.float64)
    g.opacity_logits = torch.minimum(o, reset_cap_logits(ls, var, 0.01))
    drawn = filtered(g, var).opacities
    before = filtered(replace_opacity(g, o), var).opacities
    assert torch.allclose(drawn, torch.minimum(before, torch.tensor(0.01, dtype=torch.float64)), rtol=1e-9)
    assert g.opacity_logits[0].item() == 0.0 and drawn[1].item() == pytest.approx(0.01)


def replace_opacity(g: Gaussians, o: torch.Tensor) -> Gaussians:
    from dataclasses import replace

    return replace(g, opacity_logits=o)
