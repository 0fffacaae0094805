"""Density control: clone, split (layout children stay in their plane), prune, cap, Adam rows."""

from __future__ import annotations

import math

import pytest
import torch

import splatting
from gaussians.densify import DensifyStats, densify_and_prune, gradient_scale, reset_opacity
from gaussians.losses import l1_loss
from gaussians.model import Gaussians
from gaussians.optim import Adam, expon_lr

EXTENT = 2.0  # percent_dense 0.01 -> clone below 2 cm, split above


def make(n_small=2, n_big=2, n_layout=3):
    """Small free Gaussians, big free ones, big layout ones on the plane y = -2 (normal +y)."""
    gen = torch.Generator().manual_seed(0)
    n = n_small + n_big + n_layout
    means = torch.randn(n, 3, generator=gen)
    log_scales = torch.full((n, 3), math.log(0.005))
    log_scales[n_small:] = math.log(0.2)
    is_layout = torch.zeros(n, dtype=torch.bool)
    is_layout[n_small + n_big:] = True
    normals = torch.zeros(n, 3)
    normals[is_layout] = torch.tensor([0.0, 1.0, 0.0])
    u0 = means.clone()
    u0[is_layout, 1] = -2.0
    means[is_layout] = u0[is_layout] + torch.tensor([0.05, 0.0, -0.02])  # moved within the plane
    # layout discs: random rotation about the normal would also be fine; use a tilted one to be strict
    quats = torch.randn(n, 4, generator=gen)
    g = Gaussians.create(means, sh_degree=1, log_scales=log_scales, quats=quats, is_layout=is_layout,
                         normals=normals, u0=u0)
    g.opacity_logits = torch.full((n,), 2.0)
    return g


def stats_with(g, hot):
    s = DensifyStats.zeros(len(g))
    grad = torch.zeros(len(g), 2)
    grad[hot, 0] = 1e-3
    s.add(grad, torch.ones(len(g), dtype=torch.bool), torch.full((len(g),), 4, dtype=torch.int32), pixel_scale=100.0)
    return s


def run(g, stats, opt=None, **kw):
    args = dict(grad_threshold=2e-4, percent_dense=0.01, extent=EXTENT, min_opacity=0.005,
                generator=torch.Generator().manual_seed(1))
    args.update(kw)
    return densify_and_prune(g, opt, stats, **args)


def test_clone_copies_small_hot_gaussians():
    g = make()
    hot = torch.tensor([True, False, False, False, False, False, False])
    res = run(g, stats_with(g, hot))
    h = res.gaussians
    assert (res.cloned, res.split, res.pruned) == (1, 0, 0)
    assert len(h) == len(g) + 1
    for k, v in g.tensors().items():
        assert torch.equal(getattr(h, k)[: len(g)], v)
        assert torch.equal(getattr(h, k)[-1], v[0])


def test_split_replaces_big_gaussians_by_two_smaller_children_nearby():
    g = make()
    hot = torch.tensor([False, False, True, False, False, False, False])
    res = run(g, stats_with(g, hot))
    h = res.gaussians
    assert (res.cloned, res.split, res.pruned) == (0, 1, 0)
    assert len(h) == len(g) + 1
    kids = h.means[-2:]
    assert not torch.equal(kids[0], kids[1])
    assert torch.all((kids - g.means[2]).norm(dim=1) < 4 * 0.2 * math.sqrt(3))
    torch.testing.assert_close(h.scales[-2:], torch.full((2, 3), 0.2 / 1.6))
    # the parent is gone, the others kept in order
    keep = [0, 1, 3, 4, 5, 6]
    assert torch.equal(h.means[:6], g.means[keep])


def test_split_layout_children_stay_in_plane_and_inherit():
    g = make()
    hot = torch.zeros(len(g), dtype=torch.bool)
    hot[4:] = True
    res = run(g, stats_with(g, hot))
    h = res.gaussians
    assert res.split == 3 and len(h) == len(g) + 3
    kids = slice(len(h) - 6, len(h))
    assert h.is_layout[kids].all()
    torch.testing.assert_close(h.normals[kids], torch.tensor([[0.0, 1.0, 0.0]]).expand(6, 3))
    parents = torch.tensor([4, 5, 6]).repeat(2)
    assert torch.equal(h.u0[kids], g.u0[parents])
    # in the plane: the children's offset from u0 has no normal component
    off = h.means[kids] - h.u0[kids]
    assert torch.allclose(off[:, 1], torch.zeros(6), atol=1e-6)
    assert (h.means[kids] - g.means[parents]).norm(dim=1).min() > 1e-4  # they did move
    # and a free Gaussian's split is not constrained
    g2 = make()
    hot2 = torch.zeros(len(g2), dtype=torch.bool)
    hot2[2] = True
    h2 = run(g2, stats_with(g2, hot2)).gaussians
    assert (h2.means[-2:, 1] - g2.means[2, 1]).abs().max() > 1e-4


def test_clone_of_a_layout_gaussian_keeps_its_plane_data():
    g = make()
    g.log_scales[4] = math.log(0.005)
    hot = torch.zeros(len(g), dtype=torch.bool)
    hot[4] = True
    h = run(g, stats_with(g, hot)).gaussians
    assert h.is_layout[-1] and torch.equal(h.u0[-1], g.u0[4]) and torch.equal(h.normals[-1], g.normals[4])


def test_prune_transparent_and_oversized():
    g = make()
    g.opacity_logits[1] = -10.0  # opacity 4.5e-5 < 0.005
    g.log_scales[3] = math.log(5.0)
    res = run(g, stats_with(g, torch.zeros(len(g), dtype=torch.bool)), max_world_scale=1.0)
    assert res.pruned == 2 and len(res.gaussians) == len(g) - 2
    keep = [0, 2, 4, 5, 6]
    assert torch.equal(res.gaussians.means, g.means[keep])
    # screen-space rule: radius (radians) above the limit
    s = stats_with(g, torch.zeros(len(g), dtype=torch.bool))
    s.max_radius[0] = 0.5
    res = run(make(), s, max_screen_radius=0.3)
    assert res.pruned == 1


def test_cap_limits_growth_to_the_hottest_candidates():
    g = make()
    s = DensifyStats.zeros(len(g))
    grad = torch.zeros(len(g), 2)
    grad[:, 0] = torch.tensor([1e-3, 5e-3, 2e-3, 4e-3, 3e-3, 6e-3, 7e-4])
    s.add(grad, torch.ones(len(g), dtype=torch.bool), torch.ones(len(g), dtype=torch.int32), 1.0)
    res = run(g, s, max_gaussians=len(g) + 2)
    assert len(res.gaussians) == len(g) + 2
    # the two hottest (indices 5: split, 1: clone) were chosen
    assert (res.cloned, res.split) == (1, 1)
    assert torch.equal(res.gaussians.means[len(g) - 1], g.means[1])


def test_stats_normalise_by_pixels_per_radian_and_count_visible_views():
    s = DensifyStats.zeros(3)
    vis = torch.tensor([True, True, False])
    radii = torch.tensor([3, 0, 5], dtype=torch.int32)
    s.add(torch.tensor([[3e-4, 4e-4], [1.0, 1.0], [1.0, 1.0]]), vis, radii, pixel_scale=40.0)
    s.add(torch.tensor([[0.0, 0.0], [1.0, 1.0], [1.0, 1.0]]), vis, radii, pixel_scale=40.0)
    torch.testing.assert_close(s.mean_grad(), torch.tensor([5e-4 * 40 / 2, 0.0, 0.0]))
    torch.testing.assert_close(s.count, torch.tensor([2.0, 0.0, 0.0]))
    torch.testing.assert_close(s.max_radius, torch.tensor([3 / 40, 0.0, 0.0]))
    # the same screen motion at twice the resolution: half the pixel gradient, twice the pixels/radian
    a, b = DensifyStats.zeros(1), DensifyStats.zeros(1)
    one = torch.ones(1, dtype=torch.bool)
    a.add(torch.tensor([[2e-4, 0.0]]), one, torch.ones(1, dtype=torch.int32), 256 / (2 * math.pi))
    b.add(torch.tensor([[1e-4, 0.0]]), one, torch.ones(1, dtype=torch.int32), 512 / (2 * math.pi))
    torch.testing.assert_close(a.mean_grad(), b.mean_grad())


def test_adam_rows_follow_densification_and_opacity_reset():
    g = make()
    g.requires_grad_(True)
    opt = Adam({"means": 0.01, "quats": 0.001, "log_scales": 0.005, "opacity_logits": 0.05, "sh_dc": 0.0025,
                "sh_rest": 0.000125})
    (g.means.sum() + g.opacity_logits.sum()).backward()
    opt.step(g)
    Adam.zero_grad(g)
    before = opt.exp_avg["means"].clone()
    g.opacity_logits.data[1] = -10.0
    hot = torch.zeros(len(g), dtype=torch.bool)
    hot[0] = True
    res = run(g, stats_with(g, hot), opt)
    h = res.gaussians
    assert h.means.requires_grad
    assert opt.exp_avg["means"].shape == h.means.shape
    # kept rows keep their moments; the clone starts at zero
    assert torch.equal(opt.exp_avg["means"][:-1], before[[0, 2, 3, 4, 5, 6]])
    assert torch.all(opt.exp_avg["means"][-1] == 0)
    reset_opacity(h, opt)
    assert torch.all(h.opacities <= 0.01 + 1e-6)
    assert torch.all(opt.exp_avg["opacity_logits"] == 0)


def test_adam_matches_torch_and_lr_schedule():
    torch.manual_seed(0)
    w0 = torch.randn(5, 3)
    ours = Gaussians.create(w0.clone(), sh_degree=0).requires_grad_(True)
    ref = w0.clone().requires_grad_(True)
    opt = Adam({"means": 0.01})
    topt = torch.optim.Adam([ref], lr=0.01, eps=1e-15)
    for _ in range(20):
        ((ours.means - 1.0) ** 2 * torch.arange(3.0)).sum().backward()
        opt.step(ours)
        Adam.zero_grad(ours)
        topt.zero_grad()
        ((ref - 1.0) ** 2 * torch.arange(3.0)).sum().backward()
        topt.step()
    torch.testing.assert_close(ours.means.detach(), ref.detach(), rtol=1e-6, atol=1e-7)
    assert expon_lr(0, 1.6e-4, 1.6e-6, 1000) == 1.6e-4
    assert math.isclose(expon_lr(500, 1.6e-4, 1.6e-6, 1000), 1.6e-5, rel_tol=1e-9)
    assert math.isclose(expon_lr(5000, 1.6e-4, 1.6e-6, 1000), 1.6e-6, rel_tol=1e-9)


def _statistic_at_latitude(lat_deg: float) -> float:
    """The densification statistic of one Gaussian 3 m away at latitude `lat_deg` whose target is
    the same Gaussian 0.5° further up its meridian: the same error on the sphere at any latitude."""
    cam, eye = splatting.EquirectCamera(128, 256), torch.eye(4, dtype=torch.float64)

    def at(deg):
        a = math.radians(deg)
        return torch.tensor([[0.0, -3 * math.sin(a), 3 * math.cos(a)]], dtype=torch.float64)

    rest = (torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64), torch.full((1, 3), 0.15, dtype=torch.float64),
            torch.tensor([0.9], dtype=torch.float64), torch.tensor([[1.0, 0.8, 0.6]], dtype=torch.float64))
    target = splatting.render(at(lat_deg + 0.5), *rest, eye, cam, backend="torch").image
    out = splatting.render(at(lat_deg).requires_grad_(True), *rest, eye, cam, backend="torch")
    out.means2d.retain_grad()
    l1_loss(out.image, target).backward()
    stats = DensifyStats.zeros(1, dtype=torch.float64)
    stats.add(out.means2d.grad, out.visible, out.radii, cam.pixel_scale[0], gradient_scale(cam))
    return float(stats.mean_grad()[0])


def test_panorama_statistic_weighs_latitude_as_the_pixel_mean_does():
    """The statistic follows the loss it is the gradient of: a mean over equirectangular pixels
    weighs latitude θ by 1/cos θ per steradian, and so does the statistic (docs/training.md: a
    per-steradian statistic, × cos θ, was measured on a real capture and lost)."""
    equator = _statistic_at_latitude(0.0)
    assert equator > 1e-3
    assert _statistic_at_latitude(60.0) / equator == pytest.approx(2.0, rel=0.03)
    assert _statistic_at_latitude(75.0) / equator == pytest.approx(1 / math.cos(math.radians(75)), rel=0.06)
