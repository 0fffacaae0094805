"""The random turn's Triton kernel (gaussians/turn_triton.py) against the torch path it replaces on
a GPU (TurnMaps.maps + turn_panorama through grid_sample): across the ±180° seam, at the poles,
bicubic and bilinear, masks included. Without CUDA the kernel runs in the Triton interpreter."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from gaussians.view_jitter import TurnMaps, random_turn, turn_panorama, turn_view_images
from panogeom.rotate import yaw_matrix
from splatting import devices, turn_triton

# `cuda`: `make gpu-check` runs these with the compiled kernels
pytestmark = [pytest.mark.skipif(not turn_triton.available(), reason="triton is not installed"),
              pytest.mark.cuda]
DEVICE = torch.device("cuda" if torch.cuda.is_available() else "cpu")


def _reference(image, rot, mode):
    """grid_sample in float64 (cv2 serves float32 on the CPU): the sampling the kernel copies."""
    maps = TurnMaps(*image.shape[:2], device="cpu").maps(rot)
    return turn_panorama(image.double().cpu(), maps, mode).float()


@pytest.mark.parametrize("mode", ["bicubic", "bilinear"])
def test_kernel_turn_equals_grid_sample(mode):
    g = torch.Generator().manual_seed(3)
    h, w = 12, 24
    image = torch.rand(h, w, 3, generator=g)
    turns = [random_turn(30.0, g) for _ in range(2)]
    # a yaw of 179.6°: every column reads across the seam; a 90° tilt puts the poles mid-image
    turns.append(torch.from_numpy(yaw_matrix(math.radians(179.6))))
    turns.append(torch.tensor([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]], dtype=torch.float64))
    dirs = TurnMaps(h, w, device=DEVICE).dirs
    for rot in turns:
        out = turn_triton.turn(image.to(DEVICE), dirs, rot, mode, clamp01=False).cpu()
        assert float((out - _reference(image, rot, mode)).abs().max()) < 2e-5


def test_trainer_turn_takes_the_kernel_with_the_same_image_and_mask(monkeypatch):
    """turn_view_images on the kernel (as on a GPU) and on the torch path give the same turned view:
    the image clamped to [0, 1] after the bicubic overshoot, the mask valid where the bilinear
    sample reads valid pixels only."""
    g = torch.Generator().manual_seed(4)
    h, w = 10, 20
    image = torch.rand(h, w, 3, generator=g)
    image[:, 5] = 1.0  # an edge for the bicubic overshoot, clamped either way
    mask = torch.ones(h, w, dtype=torch.bool)
    mask[-3:] = False  # a nadir cap
    mask[:, 7] = False
    rot = random_turn(10.0, g)
    maps = TurnMaps(h, w, device="cpu")
    ref_img, ref_mask = turn_view_images(maps, rot, image.double(), mask, "bicubic")  # grid_sample path
    monkeypatch.setattr(devices, "KERNELS_ON_CPU", True)
    kmaps = TurnMaps(h, w, device=DEVICE)
    out_img, out_mask = turn_view_images(kmaps, rot, image.to(DEVICE), mask.to(DEVICE), "bicubic")
    assert float((out_img.cpu() - ref_img.float()).abs().max()) < 2e-5
    assert float(out_img.min()) >= 0.0 and float(out_img.max()) <= 1.0
    # the mask's threshold (0.999) may flip only where the sample is within rounding of it
    differ = out_mask.cpu() != ref_mask
    assert int(differ.sum()) <= 1, np.argwhere(differ.numpy())
