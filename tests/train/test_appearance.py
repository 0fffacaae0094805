"""Per-panorama appearance: identity at the start, learns a panorama's exposure, survives a
resume, is refused when it does not fit; the colour-fit metrics factor exposure out."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from train_helpers import load_views, rooms, small_config

from evaluation import metrics as M
from gaussians.appearance import Appearance
from gaussians.init import random_points
from gaussians.trainer import Trainer, scene_extent


def test_identity_at_the_start_and_faces_share_their_panorama():
    app = Appearance(["a", "b"])
    img = torch.rand(4, 8, 3)
    assert torch.equal(app.apply("a", img), img) and app.regulariser().item() == 0.0
    with torch.no_grad():
        app.gain[1] = torch.tensor([2.0, 1.0, 0.5])
    assert torch.allclose(app.apply("b/px", img), img * torch.tensor([2.0, 1.0, 0.5]))
    assert torch.equal(app.apply("a/nz", img), img)


def test_pinned_mean_stays_the_identity_exactly():
    """The projection after each step: whatever the gradients, the transforms' mean (per channel,
    over the panoramas) is the identity, each panorama's offset from it is what Adam made; one
    panorama alone is all gauge, so it stays the identity."""
    torch.manual_seed(0)
    app = Appearance(["a", "b", "c"], lr=0.05, pin_mean=True)
    free = Appearance(["a", "b", "c"], lr=0.05, pin_mean=False)
    img = torch.rand(4, 8, 3)
    targets = {"a": img * 0.6, "b": img * 1.1 + 0.05, "c": img}
    for _ in range(60):
        for t in (app, free):
            sum(((t.apply(n, img) - y) ** 2).mean() for n, y in targets.items()).backward()
            t.step()
    assert torch.allclose(app.gain.detach().mean(0), torch.ones(3), atol=1e-6)
    assert torch.allclose(app.bias.detach().mean(0), torch.zeros(3), atol=1e-6)
    # the projection removes the common part only: the differences between panoramas are Adam's
    gain_a_vs_c = (app.gain[0] - app.gain[2]).detach()
    assert bool((gain_a_vs_c < -0.15).all())
    assert float((free.gain.detach().mean(0) - 1).abs().max()) > 1e-2  # unpinned, the mean drifts
    alone = Appearance(["a"], lr=0.05, pin_mean=True)
    for _ in range(5):
        ((alone.apply("a", img) - img * 0.5) ** 2).mean().backward()
        alone.step()
    assert torch.equal(alone.gain.detach(), torch.ones(1, 3)) and torch.equal(alone.bias.detach(), torch.zeros(1, 3))


def test_gradient_reaches_gain_and_bias():
    app = Appearance(["a"])
    img, target = torch.rand(4, 8, 3), torch.rand(4, 8, 3)
    ((app.apply("a", img) - target) ** 2).mean().backward()
    assert app.gain.grad is not None and float(app.gain.grad.abs().sum()) > 0
    assert app.bias.grad is not None and float(app.bias.grad.abs().sum()) > 0


def test_state_round_trip_and_refusals():
    app = Appearance(["a", "b"], lr=0.1)
    img, target = torch.rand(4, 8, 3), torch.rand(4, 8, 3) * 0.5
    for _ in range(3):
        ((app.apply("a", img) - target) ** 2).mean().backward()
        app.step()
    state = app.state_dict()
    other = Appearance(["a", "b"], lr=0.1)
    other.load_state_dict(state)
    assert torch.equal(other.gain, app.gain) and torch.equal(other.bias, app.bias)
    assert other.opt.state_dict()["state"][0]["exp_avg"].equal(app.opt.state_dict()["state"][0]["exp_avg"])
    with pytest.raises(ValueError, match="other panoramas"):
        Appearance(["a", "c"]).load_state_dict(state)
    bad = dict(state, gain=torch.full((2, 3), float("nan")))
    with pytest.raises(ValueError, match="finite"):
        other.load_state_dict(bad)
    with pytest.raises(ValueError):
        other.load_state_dict({"names": ["a", "b"]})


def darkened(views, name: str, gain: float):
    return [dataclasses.replace(v, image=v.image * gain) if v.name == name else v for v in views]


def test_training_learns_a_darker_panoramas_exposure(tiny_room):
    views = load_views(tiny_room)
    dark = views[0].name
    views = darkened(views, dark, 0.6)
    g = random_points(600, 0, rooms=rooms(tiny_room))
    # 200 iterations: at 120 the separation depended on float rounding (densification decisions in the
    # first iterations); from 200 it is clear with either kernel (ratio ~0.77)
    cfg = small_config(iterations=200, extent=scene_extent(g.means), lambda_layout=0.0, appearance=True,
                       lr_appearance=0.01)
    tr = Trainer(g, views, cfg)
    tr.train()
    gains = {n: float(np.mean(d["gain"])) for n, d in tr.appearance.as_dict().items()}
    others = [v for n, v in gains.items() if n != dark]
    # the darkened panorama's gain is the lowest, well below the others' (0.6 of them in truth)
    assert gains[dark] < 0.92 * min(others), gains
    # off: no transform at all
    assert Trainer(g, views, cfg.with_settings(appearance=False)).appearance is None


def test_resume_restores_the_transforms(tiny_room, tmp_path):
    views = load_views(tiny_room)
    g = random_points(300, 1, rooms=rooms(tiny_room))
    cfg = small_config(iterations=12, appearance=True, lr_appearance=0.01, seed=2)
    full = Trainer(g, views, cfg)
    full.train()
    ckpt = tmp_path / "ckpt.pt"
    first = Trainer(g, views, cfg)

    def stop(t, info):
        if t.iteration == 6:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        first.train(on_step=stop, checkpoint_path=ckpt)
    resumed = Trainer(g, views, cfg)
    resumed.load_checkpoint(ckpt)
    resumed.train()
    assert torch.equal(resumed.appearance.gain, full.appearance.gain)
    assert torch.equal(resumed.appearance.bias, full.appearance.bias)
    with pytest.raises(ValueError):  # a checkpoint with transforms does not resume a run without
        Trainer(g, views, cfg.with_settings(appearance=False)).load_checkpoint(ckpt)


def test_colour_fit_metrics_factor_out_exposure_but_not_structure():
    rng = np.random.default_rng(0)
    gt = rng.random((16, 32, 3)) * 0.8
    exposed = np.clip(gt * np.array([0.7, 0.8, 0.9]) + 0.05, 0, 1)
    assert M.psnr(exposed, gt) < 25
    assert M.psnr(M.colour_fit(exposed, gt), gt) > 60
    blurred = exposed.copy()
    blurred[4:12] = blurred[4:12].mean(axis=(0, 1))
    assert M.psnr(M.colour_fit(blurred, gt), gt) < 25  # structure errors stay
    mask = np.ones((16, 32), bool)
    mask[:4] = False
    wild = exposed.copy()
    wild[:4] = 1.0
    assert M.psnr(M.colour_fit(wild, gt, mask), gt, mask=mask) == pytest.approx(
        M.psnr(M.colour_fit(exposed, gt, mask), gt, mask=mask))
