"""Randomly turned panoramas: supervision between the pixel centres.

A panorama trained as it is samples the model at the same W×H directions every iteration: a
Gaussian is constrained only where it covers one of those pixel centres, so thin splats through
the centres, with gaps between them, fit every training view and leave holes that a new
viewpoint sees (docs/training.md, "Sparse captures"). The perspective crops of the baseline do
not have this freedom: their pixels fall between the panorama's, with the ground truth
interpolated there.

The trainer (`Trainer._turned`, train parameter `random_turns`) gives a training panorama a
random rotation R of its camera frame (`random_turn`) each time it is drawn: the render looks
along R d for the pixel whose direction was d, and the ground truth and mask are the panorama
resampled the same way (`TurnGrid`, `turn_panorama`: `panogeom.rotate_equirect`'s
out(d) = image(Rᵀ d), bicubic or bilinear), periodic across the ±180° seam. R is a free turn about
the vertical (a fractional pixel of longitude, as any whole-pixel part is an exact column roll)
after a tilt of at most `max_tilt_deg` about a random horizontal axis, which moves the sampling
between rows.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from scipy.spatial.transform import Rotation

from panogeom.equirect import ray_directions
from panogeom.rotate import yaw_matrix

__all__ = ["random_turn", "turn_panorama", "TurnGrid"]

_PAD = 2  # wrapped columns on each side: bicubic reads two pixels either way


def random_turn(max_tilt_deg: float, generator: torch.Generator) -> torch.Tensor:
    """[3,3] float64 rotation: a uniform yaw about +y after a tilt by an angle uniform in
    [0, max_tilt_deg] about a uniformly oriented horizontal axis."""
    yaw, axis_angle, tilt = torch.rand(3, generator=generator, dtype=torch.float64).tolist()
    a = 2.0 * math.pi * axis_angle
    tilt_vec = math.radians(max_tilt_deg) * tilt * np.array([math.cos(a), 0.0, math.sin(a)])
    return torch.from_numpy(yaw_matrix(2.0 * math.pi * yaw) @ Rotation.from_rotvec(tilt_vec).as_matrix())


class TurnGrid:
    """The unit ray directions of an H×W panorama's pixel centres (DESIGN.md's mapping), kept on
    the images' device in float32 (a column's fraction is then exact to ~1e-4 pixel at W = 2048),
    and the `grid_sample` grid of a turned copy."""

    def __init__(self, height: int, width: int, device):
        self.height, self.width = int(height), int(width)
        self.dirs = torch.from_numpy(ray_directions(self.height, self.width)).to(device=device, dtype=torch.float32)

    def grid(self, rotation: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
        """[1,H,W,2] sampling grid into the panorama padded by two wrapped columns on each side:
        pixel (u, v) of the turned panorama reads direction Rᵀ d(u, v) of the original."""
        h, w = self.height, self.width
        src = self.dirs @ rotation.to(self.dirs)  # row vectors: (Rᵀ d)ᵀ = dᵀ R
        x, y, z = src.unbind(-1)
        # column and row of DESIGN.md's mapping, then the grid's [-1, 1] over the padded image
        col = torch.atan2(x, z).mul_(w / (2.0 * math.pi)).add_(w / 2.0)  # col + 0.5, in [0, w]
        gx = torch.remainder(col, w).add_(_PAD - 0.5).mul_(2.0 / (w - 1 + 2 * _PAD)).sub_(1.0)
        row = torch.atan2(-y, torch.hypot(x, z)).mul_(-h / math.pi).add_(h / 2.0 - 0.5)
        gy = row.clamp_(0.0, h - 1.0).mul_(2.0 / max(h - 1, 1)).sub_(1.0)
        return torch.stack([gx, gy], -1)[None].to(dtype)


def turn_panorama(image: torch.Tensor, grid: torch.Tensor, mode: str = "bilinear") -> torch.Tensor:
    """[H,W,C] panorama resampled on `grid` (TurnGrid.grid), periodic across the seam; `mode`
    "bilinear" or "bicubic" (sharper; may overshoot [0, 1] at edges)."""
    padded = torch.cat([image[:, -_PAD:], image, image[:, :_PAD]], dim=1).permute(2, 0, 1)[None]
    out = F.grid_sample(padded, grid, mode=mode, padding_mode="border", align_corners=True)
    return out[0].permute(1, 2, 0)
