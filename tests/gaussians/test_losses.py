"""L_layout (value and gradient, including the 0/0 at μ = u0), SSIM and PSNR."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from gaussians.losses import layout_loss, photometric_loss, psnr, ssim


def test_layout_loss_at_u0_is_zero_with_a_finite_gradient():
    u0 = torch.tensor([[1.0, 2.0, 3.0], [0.5, -1.0, 2.0]], dtype=torch.float64)
    mu = u0.clone().requires_grad_(True)
    n = torch.tensor([[0.0, 1.0, 0.0], [0.0, 0.0, -2.0]], dtype=torch.float64)
    val = layout_loss(mu, u0, n)
    (grad,) = torch.autograd.grad(val, mu)
    assert val.item() == 0.0
    assert torch.all(torch.isfinite(grad))
    assert torch.all(grad == 0)
    # the same in float32, as in training
    mu32 = u0.float().clone().requires_grad_(True)
    (g32,) = torch.autograd.grad(layout_loss(mu32, u0.float(), n.float()), mu32)
    assert torch.all(torch.isfinite(g32))


def test_layout_loss_is_the_cosine_to_the_normal():
    u0 = torch.zeros(4, 3, dtype=torch.float64)
    n = torch.tensor([[0.0, 2.0, 0.0]] * 4, dtype=torch.float64)  # need not be unit
    mu = torch.tensor([[0.3, 0.0, 0.4],  # in the plane: 0
                       [0.0, -0.7, 0.0],  # along the normal: 1
                       [1.0, 1.0, 0.0],  # 45 degrees
                       [0.0, 0.1, math.sqrt(3) * 0.1]], dtype=torch.float64)  # 60 degrees
    vals = [layout_loss(mu[i : i + 1], u0[i : i + 1], n[i : i + 1]).item() for i in range(4)]
    assert vals == pytest.approx([0.0, 1.0, math.sqrt(0.5), 0.5], abs=1e-12)
    assert layout_loss(mu, u0, n).item() == pytest.approx(sum(vals) / 4, abs=1e-12)
    # the mask selects layout Gaussians only
    assert layout_loss(mu, u0, n, torch.tensor([False, True, False, False])).item() == pytest.approx(1.0)
    empty = layout_loss(mu.requires_grad_(True), u0, n, torch.zeros(4, dtype=torch.bool))
    assert empty.item() == 0.0 and empty.requires_grad


def test_layout_loss_gradient_matches_finite_differences():
    gen = torch.Generator().manual_seed(0)
    u0 = torch.randn(6, 3, generator=gen, dtype=torch.float64)
    mu = (u0 + 0.3 * torch.randn(6, 3, generator=gen, dtype=torch.float64)).requires_grad_(True)
    n = torch.randn(6, 3, generator=gen, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda m: layout_loss(m, u0, n), (mu,))
    # analytic: d/dmu |n.d|/(|n||d|) = sign(n.d) (n/(|n||d|) - (n.d) d/(|n||d|^3))
    d = (mu - u0).detach()
    nd = (n * d).sum(-1, keepdim=True)
    dn, nn = d.norm(dim=-1, keepdim=True), n.norm(dim=-1, keepdim=True)
    expect = torch.sign(nd) * (n / (nn * dn) - nd * d / (nn * dn**3)) / 6
    (got,) = torch.autograd.grad(layout_loss(mu, u0, n), mu)
    torch.testing.assert_close(got, expect, rtol=1e-9, atol=1e-12)


def _ssim_reference(x, y):
    """SSIM with scipy's Gaussian filter (σ 1.5, radius 5, zero outside): an independent check."""
    from scipy.ndimage import gaussian_filter

    def f(img):
        return np.stack([gaussian_filter(img[..., c].astype(np.float64), 1.5, truncate=5 / 1.5, mode="constant")
                         for c in range(img.shape[-1])], -1)

    mx, my = f(x), f(y)
    sxx, syy, sxy = f(x * x) - mx**2, f(y * y) - my**2, f(x * y) - mx * my
    c1, c2 = 0.01**2, 0.03**2
    return float((((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx**2 + my**2 + c1) * (sxx + syy + c2))).mean())


def test_ssim_and_psnr_references():
    gen = torch.Generator().manual_seed(1)
    a = torch.rand(32, 64, 3, generator=gen)
    assert ssim(a, a).item() == pytest.approx(1.0, abs=1e-6)
    b = (a + 0.1 * torch.randn(32, 64, 3, generator=gen)).clamp(0, 1)
    assert ssim(a, b).item() == pytest.approx(_ssim_reference(a.numpy(), b.numpy()), abs=1e-5)
    worse = (a + 0.3 * torch.randn(32, 64, 3, generator=gen)).clamp(0, 1)
    assert ssim(a, worse).item() < ssim(a, b).item() < 1.0
    assert psnr(a, a) == pytest.approx(120.0)
    c = (a + 0.1).clamp(0, 1)
    mse = float(((c - a) ** 2).mean())
    assert psnr(c, a) == pytest.approx(10 * math.log10(1 / mse), rel=1e-6)
    total, l1, s = photometric_loss(b, a)
    assert total.item() == pytest.approx(0.8 * (b - a).abs().mean().item() + 0.2 * (1 - s.item()), rel=1e-6)


def test_solid_angle_weight_is_cos_latitude_with_mean_one():
    from gaussians.losses import solid_angle_weight

    w = solid_angle_weight(8, 16, dtype=torch.float64)
    assert w.shape == (8, 16) and w.mean().item() == pytest.approx(1.0)
    lat = (0.5 - (np.arange(8) + 0.5) / 8) * math.pi
    ratio = w[:, 0].numpy() / np.cos(lat)
    assert np.allclose(ratio, ratio[0])  # proportional to each row's solid angle
    assert torch.all(w[:, 0] == w[:, 5])  # constant along a row


def test_photometric_loss_weighted_means():
    from gaussians.losses import ssim_map

    g = torch.Generator().manual_seed(0)
    a, b = torch.rand(12, 20, 3, generator=g, dtype=torch.float64), torch.rand(12, 20, 3, generator=g,
                                                                               dtype=torch.float64)
    # uniform weights: exactly the plain means
    plain = photometric_loss(a, b)
    flat = photometric_loss(a, b, weight=torch.full((12, 20), 3.0, dtype=torch.float64))
    for x, y in zip(plain, flat):
        assert x.item() == pytest.approx(y.item(), rel=1e-12)
    assert ssim_map(a, b).mean().item() == pytest.approx(ssim(a, b).item(), rel=1e-12)
    # all weight on one row: that row's L1 and SSIM, masked pixels excluded
    w = torch.zeros(12, 20, dtype=torch.float64)
    w[3] = 1.0
    mask = torch.ones(12, 20, dtype=torch.bool)
    mask[3, :10] = False
    _, l1, s = photometric_loss(a, b, weight=w, mask=mask)
    assert l1.item() == pytest.approx((a - b)[3, 10:].abs().mean().item(), rel=1e-12)
    assert s.item() == pytest.approx(ssim_map(a, b, mask=mask)[3, 10:].mean().item(), rel=1e-12)


def test_weighted_and_batched_ssim_gradients_are_exact():
    """SSIM's closed-form gradient with per-pixel weights ([H,W], and [B,H,W] with a batch mask, as
    the crop loss calls it) against finite differences, and its value against the map."""
    from gaussians.losses import ssim_map

    g = torch.Generator().manual_seed(3)
    gt = torch.rand(9, 11, 3, generator=g, dtype=torch.float64)
    pred = torch.rand(9, 11, 3, generator=g, dtype=torch.float64, requires_grad=True)
    w = torch.rand(9, 11, generator=g, dtype=torch.float64)
    assert ssim(pred, gt, weight=w).item() == pytest.approx(
        (ssim_map(pred, gt) * w).sum().item() / w.sum().item(), rel=1e-12)
    assert torch.autograd.gradcheck(lambda p: ssim(p, gt, weight=w), (pred,))
    gb = torch.rand(2, 3, 8, 8, generator=g, dtype=torch.float64)
    pb = torch.rand(2, 3, 8, 8, generator=g, dtype=torch.float64, requires_grad=True)
    mb = torch.rand(2, 8, 8, generator=g) > 0.3
    assert torch.autograd.gradcheck(lambda p: ssim(p, gb, mask=mb), (pb,))
    # the masked batch mean is the mean of the valid pixels' map values over both images
    want = sum(ssim_map(pb[i].detach().permute(1, 2, 0), gb[i].permute(1, 2, 0), mask=mb[i])[mb[i]].sum()
               for i in range(2)) / mb.sum()
    assert ssim(pb, gb, mask=mb).item() == pytest.approx(want.item(), rel=1e-12)
