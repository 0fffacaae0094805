"""The 360 path's controls for sparse captures (docs/training.md "Sparse captures: 360° against crops"):
random background, anisotropy clamp, solid-angle weighting and the projection-dependent defaults."""

from __future__ import annotations

import math

import pytest
import torch
from train_helpers import small_config

from gaussians.trainer import Trainer, clamp_anisotropy_


def test_random_background_makes_surfaces_opaque():
    """One half-transparent Gaussian before a uniformly dark-grey panorama: against the black background
    it fits the grey by darkening its colour and stays half transparent; against a random background
    every transparent pixel shows that background, so its opacity rises."""
    import splatting
    from gaussians.model import Gaussians
    from gaussians.trainer import TrainView

    g = Gaussians.create(torch.tensor([[0.0, 0.0, 1.0]]), sh_degree=0,
                         log_scales=torch.full((1, 3), math.log(0.4)))
    g.opacity_logits = torch.zeros(1)
    view = TrainView("v", torch.full((16, 32, 3), 0.2), torch.eye(4), splatting.EquirectCamera(16, 32))
    opacity = {}
    for rb in (False, True):
        cfg = small_config(iterations=150, extent=1.0, densify_until=0, lambda_layout=0.0, lambda_dssim=0.0,
                           random_background=rb)
        tr = Trainer(g, [view], cfg)
        tr.train()
        opacity[rb] = float(torch.sigmoid(tr.g.opacity_logits)[0])
    assert opacity[True] > opacity[False] + 0.1, opacity
    # the draws come from the trainer's generator: the same seed, the same run
    cfg = small_config(iterations=5, extent=1.0, densify_until=0, random_background=True)
    a, b = Trainer(g, [view], cfg), Trainer(g, [view], cfg)
    a.train(), b.train()
    assert torch.equal(a.g.opacity_logits, b.g.opacity_logits) and torch.equal(a.g.sh_dc, b.g.sh_dc)


def test_clamp_anisotropy_shortens_only_the_longest_axis():
    ls = torch.log(torch.tensor([[1.0, 10.0, 2.0], [1.0, 1.0, 0.1], [3.0, 1.0, 1.0]]))
    clamp_anisotropy_(ls, 4.0)
    s = torch.exp(ls)
    assert torch.allclose(s, torch.tensor([[1.0, 8.0, 2.0], [1.0, 1.0, 0.1], [3.0, 1.0, 1.0]]))
    top = s.sort(dim=1, descending=True).values
    assert torch.all(top[:, 0] <= 4.0 * top[:, 1] * (1 + 1e-6))


def test_projection_defaults():
    """Parameters left unset take the projection's default; set ones win."""
    from stages.train import PROJECTION_DEFAULTS, Params, make_config

    assert set(PROJECTION_DEFAULTS) == {"360", "crops", "cubemap"}
    for proj, defaults in PROJECTION_DEFAULTS.items():
        p = Params(projection=proj)
        cfg = make_config(p, 4, 2.0)
        assert cfg.render.random_background == defaults["random_background"]
        assert cfg.turns.random_turns == defaults["random_turns"] and cfg.render.eps2d == defaults["eps2d"]
        # lr_scale multiplies every learning rate
        for name in ("lr_position_init", "lr_position_final", "lr_sh_dc", "lr_sh_rest", "lr_opacity",
                     "lr_scaling", "lr_rotation"):
            assert getattr(cfg.optim, name) == pytest.approx(defaults["lr_scale"] * getattr(p, name))
    assert make_config(Params(lr_scale=1.0), 4, 1.0).optim.lr_opacity == Params().lr_opacity
    assert make_config(Params(projection="360", random_background=True), 4, 1.0).render.random_background is True
    assert make_config(Params(projection="crops", random_background=True), 4, 1.0).render.random_background is True
    assert (PROJECTION_DEFAULTS["360"]["random_turns"], PROJECTION_DEFAULTS["360"]["eps2d"]) == (True, 0.05)
    assert (PROJECTION_DEFAULTS["crops"]["random_turns"], PROJECTION_DEFAULTS["crops"]["eps2d"]) == (False, 0.3)
    cfg = make_config(Params(random_turns=False, random_turn_tilt_deg=5, eps2d=0.1, random_turn_interp="bilinear"),
                      4, 1.0)
    assert (cfg.turns.random_turns, cfg.turns.random_turn_tilt_deg, cfg.render.eps2d, cfg.turns.random_turn_interp) == (
        False, 5, 0.1, "bilinear")


def test_every_shared_setting_reaches_the_trainer():
    """make_config passes each setting the stage shares with TrainConfig through (the learning rates
    times lr_scale), and a setting left at its default is the trainer's own default."""

    from gaussians.config import TrainConfig
    from stages.train import _SCALED_LRS, Params, make_config

    trainer_default = TrainConfig().flat()
    derived = {"iterations", "densify_from", "densify_until", "opacity_reset_every", "max_gaussians", "eps2d",
               "random_turns", "mip_filter", "random_background", "lambda_layout", "coverage_height", "extent",
               "background", "device"}  # resolved from the preset / projection, or derived by the stage
    shared = [name for name in TrainConfig.setting_names() if name in Params.model_fields]
    assert len(shared) > 40
    for name in shared:
        if name in derived or Params.model_fields[name].default is None:
            continue
        assert Params.model_fields[name].default == trainer_default[name], name
        value = trainer_default[name]
        changed = (not value) if isinstance(value, bool) else (
            value if isinstance(value, str) else (tuple(0.5 for _ in value) if isinstance(value, tuple)
                                                  else value * 3 + 1 if isinstance(value, int) else value * 0.5 + 1e-4))
        if name == "random_turn_interp":
            changed = "bilinear"
        if name == "sh_degree":
            changed = 1
        if name == "tile_size":
            changed = 8
        cfg = make_config(Params(**{name: changed, "lr_scale": 0.25}), 4, 2.0)
        expected = 0.25 * changed if name in _SCALED_LRS else changed
        assert cfg.flat()[name] == pytest.approx(expected), name


def test_crop_resampler_matches_the_baselines_crops_and_passes_gradients():
    """The differentiable resampling gives the crops the baseline trains on (panogeom.resample.perspective_crop,
    cv2.remap), and the crop loss of a panorama against its own crops is 0 (SSIM 1)."""
    import numpy as np

    import splatting
    from gaussians.crop_loss import CropResampler, crop_photometric_loss
    from panogeom.resample import perspective_crop

    h = 24
    img = np.random.default_rng(0).random((h, 2 * h, 3)).astype(np.float32)
    rs = CropResampler(h, 2 * h)
    ours = rs(torch.from_numpy(img)).permute(0, 2, 3, 1).numpy()
    for k, (cv, cam) in enumerate(splatting.crop_rig(h).crops()):
        assert np.abs(ours[k] - perspective_crop(img, cv.numpy(), cam)).max() < 1e-5
    pred = torch.from_numpy(img).requires_grad_(True)
    gt = rs(torch.from_numpy(img))
    loss, l1, s = crop_photometric_loss(pred, gt, rs, 0.8, 0.2)
    assert l1.item() < 1e-6 and abs(s.item() - 1.0) < 1e-5
    loss2, _, _ = crop_photometric_loss(pred, gt.flip(-1), rs, 0.8, 0.2,
                                        mask_crops=torch.ones(gt.shape[0], h, h, dtype=torch.bool))
    loss2.backward()
    assert pred.grad.abs().sum() > 0


def test_coverage_loss_closes_a_hole_no_training_view_shows():
    """A half-transparent shell of Gaussians around two cameras, no photometric loss: the coverage
    loss, rendered from points between the cameras, sees the 1 − alpha and raises the shell's
    opacity; without it nothing moves. The positions are drawn between the distinct centres."""
    import splatting
    from gaussians.model import Gaussians
    from gaussians.trainer import TrainView

    gen = torch.Generator().manual_seed(0)
    d = torch.randn(400, 3, generator=gen)
    d = d / d.norm(dim=1, keepdim=True)
    g = Gaussians.create(2.0 * d, sh_degree=0, log_scales=torch.full((400, 3), math.log(0.25)))
    g.opacity_logits = torch.full((400,), -1.0)
    cams = [torch.eye(4), torch.eye(4)]
    cams[1][:3, 3] = torch.tensor([-0.6, 0.0, 0.0])  # world-to-camera: centre at x = +0.6
    views = [TrainView(f"v{i}", torch.full((8, 16, 3), 0.3), vm, splatting.EquirectCamera(8, 16))
             for i, vm in enumerate(cams)]
    opacity, logs = {}, {}
    for lam in (0.0, 1.0):
        cfg = small_config(iterations=40, extent=2.0, densify_until=0, lambda_layout=0.0, lambda_dssim=0.0,
                           lambda_l1=0.0, lambda_coverage=lam, coverage_height=8)
        tr = Trainer(g, views, cfg)
        centres = tr.objective.camera_centres()
        assert torch.allclose(centres.sort(dim=0).values[:, 0], torch.tensor([0.0, 0.6]), atol=1e-6)
        tr.train()
        opacity[lam] = float(torch.sigmoid(tr.g.opacity_logits.detach()).mean())
        logs[lam] = [r.get("coverage") for r in tr.records]
    assert opacity[0.0] == pytest.approx(torch.sigmoid(torch.tensor(-1.0)).item(), abs=1e-6)
    assert opacity[1.0] > opacity[0.0] + 0.05, opacity
    assert all(c is None for c in logs[0.0]) and logs[1.0][-1] < logs[1.0][0]


def test_appearance_gauge_pins_the_mean_transform():
    """Two panoramas of one grey, one 1.25× the other: transforms and colours can split the
    difference any way (a free gauge); pinned by default, the mean gain is exactly 1, so the
    model's colour is the mean exposure, 0.5 × (1 + 1.25) / 2, and the transforms carry each
    panorama's exposure."""
    import splatting
    from gaussians.model import Gaussians
    from gaussians.trainer import TrainView

    g = Gaussians.create(torch.tensor([[0.0, 0.0, 1.0]]), sh_degree=0, log_scales=torch.full((1, 3), 2.0))
    g.opacity_logits = torch.full((1,), 8.0)
    views = [TrainView(f"v{i}", torch.full((8, 16, 3), 0.5 * k), torch.eye(4), splatting.EquirectCamera(8, 16))
             for i, k in enumerate((1.0, 1.25))]
    cfg = small_config(iterations=100, extent=1.0, densify_until=0, lambda_layout=0.0, lambda_dssim=0.0, lr_sh_dc=0.02,
                       appearance=True, lr_appearance=0.02, lambda_appearance=0.0, log_every=50)
    tr = Trainer(g, views, cfg)
    tr.train()
    gain = tr.appearance.gain.detach()
    assert float(tr.appearance.gauge().detach()) < 1e-12
    assert float(gain.mean()) == pytest.approx(1.0, abs=1e-6)
    with torch.no_grad():
        colour = tr.g.sh_dc[0, 0].mean().item() * 0.28209479177387814 + 0.5
    assert colour == pytest.approx(0.5 * 1.125, abs=0.02)
    # and the transforms carry each panorama's exposure
    seen = [tr.appearance.apply(f"v{i}", torch.full((1, 1, 3), colour)).mean().item() for i in range(2)]
    assert seen == pytest.approx([0.5, 0.625], abs=0.02)


def test_mip_filter_opacity_reset_caps_the_drawn_opacity():
    """With mip_filter the reset clamps the opacity as rendered (filtered) to 0.01, as Mip-Splatting."""
    import splatting
    from gaussians.model import Gaussians
    from gaussians.trainer import TrainView

    gen = torch.Generator().manual_seed(1)
    g = Gaussians.create(torch.randn(50, 3, generator=gen) + torch.tensor([0.0, 0.0, 3.0]), sh_degree=0,
                         log_scales=torch.full((50, 3), math.log(0.2)))
    g.opacity_logits = torch.full((50,), 2.0)
    view = TrainView("v", torch.full((8, 16, 3), 0.4), torch.eye(4), splatting.EquirectCamera(8, 16))
    cfg = small_config(iterations=5, extent=1.0, densify_from=100, densify_until=10, opacity_reset_every=5,
                       mip_filter=True)  # the reset runs within the densification window, as in 3DGS
    tr = Trainer(g, [view], cfg)
    tr.train()
    drawn = torch.sigmoid(tr._drawn().opacity_logits.detach())
    assert float(drawn.max()) == pytest.approx(0.01, rel=1e-4)
    assert float(torch.sigmoid(tr.g.opacity_logits.detach()).max()) > 0.01  # the raw one is higher
