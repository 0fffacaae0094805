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
resampled the same way (`TurnMaps`, `turn_panorama`: `panogeom.rotate_equirect`'s
out(d) = image(Rᵀ d), bicubic or bilinear), periodic across the ±180° seam. R is a free turn about
the vertical (a fractional pixel of longitude, as any whole-pixel part is an exact column roll)
after a tilt of at most `max_tilt_deg` about a random horizontal axis, which moves the sampling
between rows.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from scipy.spatial.transform import Rotation

from panogeom.equirect import ray_directions
from panogeom.rotate import yaw_matrix

__all__ = ["random_turn", "turn_panorama", "turn_view_images", "TurnMaps"]

_PAD = 2  # rows (cv2) or wrapped columns (grid_sample) on each side: bicubic reads two pixels either way


def random_turn(max_tilt_deg: float, generator: torch.Generator) -> torch.Tensor:
    """[3,3] float64 rotation: a uniform yaw about +y after a tilt by an angle uniform in
    [0, max_tilt_deg] about a uniformly oriented horizontal axis."""
    yaw, axis_angle, tilt = torch.rand(3, generator=generator, dtype=torch.float64).tolist()
    a = 2.0 * math.pi * axis_angle
    tilt_vec = math.radians(max_tilt_deg) * tilt * np.array([math.cos(a), 0.0, math.sin(a)])
    return torch.from_numpy(yaw_matrix(2.0 * math.pi * yaw) @ Rotation.from_rotvec(tilt_vec).as_matrix())


class TurnMaps:
    """The unit ray directions of an H×W panorama's pixel centres (DESIGN.md's mapping), kept on
    the images' device in float32 (a column's fraction is then exact to ~1e-4 pixel at W = 2048)
    and planar, [3, H·W] (the atan2s run several times faster on contiguous rows than on
    interleaved xyz), and the pixel maps of a turned copy."""

    def __init__(self, height: int, width: int, device):
        self.height, self.width = int(height), int(width)
        dirs = ray_directions(self.height, self.width).reshape(-1, 3).T
        self.dirs = torch.from_numpy(np.ascontiguousarray(dirs)).to(device=device, dtype=torch.float32)

    def maps(self, rotation: torch.Tensor) -> torch.Tensor:
        """[2,H,W] float32 (column, row) that pixel (u, v) of the turned panorama reads: the pixel
        coordinates of direction Rᵀ d(u, v) in the original, columns in [-0.5, W - 0.5] (the
        samplers wrap them), rows clamped to [0, H - 1]."""
        h, w = self.height, self.width
        x, y, z = rotation.T.to(self.dirs) @ self.dirs
        col = torch.atan2(x, z).mul_(w / (2.0 * math.pi)).add_(w / 2.0 - 0.5)
        # asin of a unit vector's y: the row's error is 0.003 pixel at the pole rows in float32, where
        # atan2(y, hypot(x, z)) would cost three times as much
        row = torch.asin(y.clamp_(-1.0, 1.0)).mul_(h / math.pi).add_(h / 2.0 - 0.5).clamp_(0.0, h - 1.0)
        return torch.stack([col, row]).view(2, h, w)


def turn_panorama(image: torch.Tensor, maps: torch.Tensor, mode: str = "bilinear") -> torch.Tensor:
    """[H,W,C] panorama resampled at `maps` (TurnMaps.maps), periodic across the seam, contiguous;
    `mode` "bilinear" or "bicubic" (sharper; may overshoot [0, 1] at edges). Bicubic in float32 on
    the CPU (what training holds) goes through cv2.remap: 3x faster than grid_sample there, with
    the same cubic kernel (a = -0.75). Everything else goes through grid_sample: cv2's cubic is
    wrong in float64 and its bilinear weights are quantised to 1/32 pixel."""
    if mode == "bicubic" and image.device.type == "cpu" and image.dtype == torch.float32:
        # rows replicated above and below, so the taps of the clamped pole rows stay inside while
        # the columns wrap
        padded = cv2.copyMakeBorder(image.contiguous().numpy(), _PAD, _PAD, 0, 0, cv2.BORDER_REPLICATE)
        col, row = maps.numpy()
        out = cv2.remap(padded, col, row + _PAD, cv2.INTER_CUBIC, borderMode=cv2.BORDER_WRAP)
        return torch.from_numpy(out.reshape(image.shape))
    h, w = image.shape[:2]
    padded = torch.cat([image[:, -_PAD:], image, image[:, :_PAD]], dim=1).permute(2, 0, 1)[None]
    gx = (maps[0] + _PAD) * (2.0 / (w - 1 + 2 * _PAD)) - 1.0
    gy = maps[1] * (2.0 / max(h - 1, 1)) - 1.0
    grid = torch.stack([gx, gy], -1)[None].to(image.dtype)
    out = F.grid_sample(padded, grid, mode=mode, padding_mode="border", align_corners=True)
    return out[0].permute(1, 2, 0).contiguous()


def turn_view_images(turn_maps: TurnMaps, rotation: torch.Tensor, image: torch.Tensor, mask: torch.Tensor | None,
                     mode: str) -> tuple[torch.Tensor, torch.Tensor | None]:
    """A training view's image ([H,W,3], clamped to [0, 1] unless bilinear) and mask ([H,W] bool,
    valid where the bilinear sample reads valid pixels only) turned by `rotation`. On a GPU (float32)
    one Triton launch each (gaussians/turn_triton.py); elsewhere `TurnMaps.maps` + `turn_panorama`."""
    from splatting import turn_triton
    from splatting.devices import takes_kernels

    if takes_kernels(image) and image.dtype == torch.float32:
        out = turn_triton.turn(image, turn_maps.dirs, rotation, mode, clamp01=mode != "bilinear")
        if mask is None:
            return out, None
        m = turn_triton.turn(mask[..., None].to(image.dtype), turn_maps.dirs, rotation, "bilinear", clamp01=False)
        return out, m[..., 0] > 0.999
    maps = turn_maps.maps(rotation)
    out = turn_panorama(image, maps, mode)
    if mode != "bilinear":
        out = out.clamp_(0.0, 1.0)
    if mask is None:
        return out, None
    return out, turn_panorama(mask[..., None].to(image.dtype), maps)[..., 0] > 0.999
