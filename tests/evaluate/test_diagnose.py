"""scripts/openmvg_sparse_scene.py's `diagnose` figures: `local_std` (the "texture" figure, the
standard deviation in SSIM's window) against closed forms, and `surface_distance_ratios` (where the
model puts the room against its layout) on a shell of known distance."""

from __future__ import annotations

import numpy as np

from tests.scripttools import load_script


def test_local_std_is_zero_on_flat_and_the_amplitude_on_fine_stripes():
    local_std = load_script("openmvg_sparse_scene").local_std
    flat = np.full((40, 60, 3), 0.37, np.float32)
    assert np.abs(local_std(flat)).max() < 1e-3
    # stripes of ±a one pixel wide: any window's mean is ~0.5 and its variance ~a² (away from the
    # border, where the replicated edge is as striped as the rest)
    a = 0.2
    stripes = np.where(np.arange(60) % 2 == 0, 0.5 + a, 0.5 - a).astype(np.float32)
    image = np.broadcast_to(stripes[None, :, None], (40, 60, 3)).copy()
    inner = local_std(image)[10:-10, 10:-10]
    np.testing.assert_allclose(inner, a, rtol=0.02)
    # the figure scales with the contrast: half the stripes' amplitude, half the deviation
    np.testing.assert_allclose(local_std(0.5 + (image - 0.5) / 2)[10:-10, 10:-10], a / 2, rtol=0.02)


def test_layout_distance_ratio_is_one_for_a_translucent_shell_on_the_layout():
    """`diagnose`'s "where the model puts the room": Gaussians exactly on a sphere of the layout's
    distance, translucent enough that alpha is well below 1, must measure 1 (render_pose's depth is
    already normalised by alpha; dividing again measured 1/alpha, i.e. 'behind the layout')."""
    import torch

    from evaluation.model_io import equirect_camera, render_pose
    from gaussians.model import Gaussians
    from panogeom.surfaces import CEILING, FLOOR, WALL

    ratios_of = load_script("openmvg_sparse_scene").surface_distance_ratios
    n, radius = 4000, 2.0
    k = np.arange(n) + 0.5  # a Fibonacci sphere: even cover, no seam or pole gaps
    y = 1 - 2 * k / n
    phi = np.pi * (1 + 5**0.5) * k
    pts = radius * np.stack([np.sqrt(1 - y**2) * np.cos(phi), y, np.sqrt(1 - y**2) * np.sin(phi)], 1)
    g = Gaussians.create(pts, log_scales=np.full((n, 3), np.log(0.05)),
                         opacity_logits=np.full(n, np.log(0.15 / 0.85)), sh_degree=0)
    h, w = 32, 64
    r = render_pose(g, np.eye(4), equirect_camera(h, w), background=torch.zeros(3))
    label = np.full((h, w), WALL)
    label[: h // 4], label[-h // 4:] = CEILING, FLOOR
    ratios = ratios_of(r, np.full((h, w), radius), label)
    opaque = r.alpha > 0.5
    assert opaque.mean() > 0.9 and np.median(1 / r.alpha[opaque]) > 1.4  # translucent: the check bites
    for name in ("ceiling", "walls", "floor"):
        assert ratios[name].size > 0
        assert abs(np.median(ratios[name]) - 1.0) < 0.02, name
