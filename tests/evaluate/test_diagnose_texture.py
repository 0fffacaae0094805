"""scripts/openmvg_sparse_scene.py's `local_std` (the diagnosis' "texture" figure): the standard
deviation in SSIM's window, checked against closed forms."""

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
