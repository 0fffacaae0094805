"""Randomly turned training panoramas (gaussians/view_jitter.py): the resampled ground truth shows
what the turned camera sees, by the renderer's own conventions."""

from __future__ import annotations

import math

import numpy as np
import torch

import splatting
from gaussians.model import Gaussians, render
from gaussians.config import TrainConfig
from gaussians.trainer import Trainer, TrainView
from gaussians.view_jitter import TurnMaps, random_turn, turn_panorama
from panogeom.rotate import rotate_equirect, yaw_matrix


def test_whole_pixel_yaw_is_an_exact_column_roll():
    img = torch.rand(16, 32, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    grid = TurnMaps(16, 32, "cpu").maps(torch.from_numpy(yaw_matrix(2 * math.pi * 5 / 32)))
    assert torch.allclose(turn_panorama(img, grid), torch.roll(img, 5, dims=1), atol=1e-5)  # float32 grid


def test_turn_agrees_with_rotate_equirect_and_inverts():
    """Same convention as panogeom.rotate_equirect (out(d) = image(Rᵀ d)); cv2's bilinear weights are
    quantised to 1/32, hence the tolerance. Turning by R then Rᵀ gives a smooth image back."""
    h, w = 48, 96
    lat, lon = np.meshgrid(np.linspace(1.5, -1.5, h), np.linspace(-math.pi, math.pi, w, endpoint=False),
                           indexing="ij")
    smooth = np.stack([0.5 + 0.4 * np.cos(lat) * np.sin(lon), 0.5 + 0.3 * np.sin(lat),
                       0.5 + 0.2 * np.cos(2 * lon) * np.cos(lat)], -1)
    img = torch.from_numpy(smooth)
    rot = random_turn(30.0, torch.Generator().manual_seed(3))
    grids = TurnMaps(h, w, "cpu")
    turned = turn_panorama(img, grids.maps(rot))
    assert np.abs(turned.numpy() - rotate_equirect(smooth, rot.numpy())).max() < 0.01
    back = turn_panorama(turned, grids.maps(rot.T))
    assert (back - img)[4:-4].abs().max() < 0.02  # two bilinear resamplings; the pole rows are clamped
    assert not torch.allclose(turned, img, atol=0.05)


def test_cpu_bicubic_resampler_matches_grid_sample():
    """Bicubic float32 on the CPU goes through cv2.remap, float64 through grid_sample: the same image,
    across the seam and at the clamped pole rows, contiguous for the losses."""
    img = torch.rand(24, 48, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(4))
    maps = TurnMaps(24, 48, "cpu").maps(random_turn(30.0, torch.Generator().manual_seed(5)))
    fast, ref = turn_panorama(img.float(), maps, "bicubic"), turn_panorama(img, maps, "bicubic")
    assert fast.dtype == torch.float32 and fast.is_contiguous() and ref.is_contiguous()
    assert (fast.double() - ref).abs().max() < 1e-5
    # one channel, as the mask is turned
    assert (turn_panorama(img[..., :1].float(), maps, "bicubic").double() - ref[..., :1]).abs().max() < 1e-5


def test_random_turn_is_a_rotation_within_its_tilt():
    g = torch.Generator().manual_seed(0)
    for tilt in (0.0, 1.0, 30.0):
        for _ in range(20):
            r = random_turn(tilt, g)
            assert torch.allclose(r @ r.T, torch.eye(3, dtype=torch.float64), atol=1e-12)
            assert torch.linalg.det(r).item() > 0
            up = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
            angle = math.degrees(math.acos(min(1.0, float(up @ r @ up))))
            assert angle <= tilt + 1e-6


def _splats(seed: int = 0) -> Gaussians:
    """Large soft splats on a shell 2 m around the origin: a smooth panorama."""
    gen = torch.Generator().manual_seed(seed)
    d = torch.nn.functional.normalize(torch.randn(300, 3, generator=gen, dtype=torch.float64), dim=1)
    g = Gaussians.create(2.0 * d, sh_degree=0, dtype=torch.float64,
                         log_scales=torch.full((300, 3), math.log(0.35), dtype=torch.float64))
    g.sh_dc = torch.rand(300, 1, 3, generator=gen, dtype=torch.float64) * 2 - 1
    g.opacity_logits = torch.full((300,), 2.0, dtype=torch.float64)
    return g


def test_turned_view_matches_the_render_of_the_turned_camera():
    """The trainer's turned view: rendering the model at its viewmat gives its (resampled) ground truth,
    for a ground truth rendered from the same model at the original camera, and its mask follows."""
    g = _splats()
    cam = splatting.EquirectCamera(32, 64)
    viewmat = torch.eye(4, dtype=torch.float64)
    viewmat[:3, 3] = torch.tensor([0.2, -0.1, 0.3], dtype=torch.float64)
    gt = render(g, viewmat, cam, backend="torch", sh_degree=0).image.detach()
    mask = torch.ones(32, 64, dtype=torch.bool)
    mask[24:] = False  # the bottom quarter masked out
    view = TrainView("pano_00", gt, viewmat, cam, mask)
    tr = Trainer(g, [view], TrainConfig.of(iterations=1, random_turns=True, random_turn_tilt_deg=20.0, backend="torch"))
    errors = []
    for _ in range(3):
        turned = tr._turned(tr.views[0])
        assert not torch.equal(turned.viewmat, viewmat)
        out = render(g, turned.viewmat, cam, backend="torch", sh_degree=0).image.detach()
        errors.append((out - turned.image)[4:-4].abs().mean().item())
        # the mask moves with the image: roughly a quarter of the pixels stay invalid
        assert 0.15 < (~turned.mask).double().mean().item() < 0.3
    assert max(errors) < 0.01
    # and the comparison is not vacuous: the unturned ground truth does not match the turned render
    assert (out - gt)[4:-4].abs().mean().item() > 5 * max(errors)


def test_bicubic_turn_rolls_exactly_and_stays_in_range():
    img = torch.rand(16, 32, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    grids = TurnMaps(16, 32, "cpu")
    roll = grids.maps(torch.from_numpy(yaw_matrix(2 * math.pi * 3 / 32)))
    assert torch.allclose(turn_panorama(img, roll, "bicubic"), torch.roll(img, 3, dims=1), atol=1e-5)
    # a half-pixel yaw: bilinear averages two neighbours (a blur), bicubic less so
    half = grids.maps(torch.from_numpy(yaw_matrix(2 * math.pi * 0.5 / 32)))
    lin, cub = turn_panorama(img, half), turn_panorama(img, half, "bicubic")
    assert torch.allclose(lin, 0.5 * (img + torch.roll(img, 1, dims=1)), atol=1e-5)
    assert cub.std() > lin.std()


def test_training_renders_use_the_configured_dilation():
    """A ground truth rendered with eps2d 0.05: the trainer's first loss is ~0 when it trains with the
    same dilation (no turns) and clearly not with the standard 0.3; the turned view carries it too."""
    g = _splats(1)
    g.log_scales = torch.full_like(g.log_scales, math.log(0.004))  # thin: the dilation shows
    cam = splatting.EquirectCamera(32, 64)
    viewmat = torch.eye(4, dtype=torch.float64)
    gt = render(g, viewmat, cam, backend="torch", sh_degree=0, eps2d=0.05).image.detach()
    losses = {}
    for eps in (0.05, 0.3):
        cfg = TrainConfig.of(iterations=1, eps2d=eps, backend="torch", lambda_dssim=0.0, layout_reg=False,
                          densify_from=10)
        tr = Trainer(g.detach(), [TrainView("pano_00", gt, viewmat, cam)], cfg)
        losses[eps] = float(tr.step()["l1"])
    assert losses[0.05] < 1e-6
    assert losses[0.3] > 1e-3
