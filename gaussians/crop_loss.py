"""The photometric loss of a rendered panorama measured on perspective crops of it.

`CropResampler` resamples an equirectangular image into the crops of a `splatting.PerspectiveRig`
(by default the paper's eight 120° crops) with bilinear `grid_sample`, differentiably: a 360 model
is then rendered as a panorama but supervised as the crops baseline is (the same crops, the same
resampling of the ground truth, L1 and 11×11 SSIM on undistorted images), every crop each iteration.
The sampling is the one `panogeom.resample.perspective_crop` does with cv2.remap (wrapping across the ±180°
seam, edge rows clamped).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

import splatting
from gaussians.losses import ssim

__all__ = ["CropResampler", "crop_photometric_loss"]


class CropResampler:
    def __init__(self, height: int, width: int, rig: splatting.PerspectiveRig | None = None,
                 dtype=torch.float32, device="cpu"):
        rig = rig or splatting.crop_rig(height)
        cam = rig.camera
        s = int(cam.height)
        c, r = np.meshgrid(np.arange(s) + 0.5, np.arange(s) + 0.5)
        d_crop = np.stack([(c - cam.cx) / cam.fx, (r - cam.cy) / cam.fy, np.ones_like(c)], -1)
        grids = []
        for rot in rig.rotations(torch.float64):
            d = d_crop @ rot.numpy()  # crop axes are the rows of rot: d_pano = rotᵀ d_crop
            phi = np.arctan2(d[..., 0], d[..., 2])
            theta = np.arctan2(-d[..., 1], np.hypot(d[..., 0], d[..., 2]))
            col = (phi / (2 * np.pi) + 0.5) * width - 0.5
            row = (0.5 - theta / np.pi) * height - 0.5
            mx = np.mod(col + 0.5, width) - 0.5 + 1.0  # one wrapped column padded on each side
            my = np.clip(row, 0, height - 1)
            grids.append(np.stack([2 * mx / (width + 1) - 1, 2 * my / max(height - 1, 1) - 1], -1))
        self.grid = torch.from_numpy(np.stack(grids)).to(dtype=dtype, device=device)  # [K,S,S,2]
        self.size = s

    def __call__(self, image: torch.Tensor) -> torch.Tensor:
        """[H,W,C] panorama -> [K,C,S,S] crops."""
        padded = torch.cat([image[:, -1:], image, image[:, :1]], dim=1).permute(2, 0, 1)[None]
        k = self.grid.shape[0]
        return F.grid_sample(padded.expand(k, -1, -1, -1), self.grid.to(image.dtype), mode="bilinear",
                             padding_mode="border", align_corners=True)


def crop_photometric_loss(pred: torch.Tensor, gt_crops: torch.Tensor, resampler: CropResampler,
                          lambda_l1: float, lambda_dssim: float, mask_crops: torch.Tensor | None = None
                          ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(λ1·L1 + λ2·(1−SSIM), L1, SSIM) of the panorama `pred` [H,W,3] resampled into the crops against
    `gt_crops` [K,3,S,S] (the ground truth resampled the same way); `mask_crops` [K,S,S] bool."""
    p = resampler(pred)
    if mask_crops is None:
        l1 = (p - gt_crops).abs().mean()
        s = ssim(p, gt_crops) if lambda_dssim > 0 else pred.new_tensor(1.0)
    else:
        m = mask_crops[:, None].to(p.dtype)
        n = m.sum().clamp_min(1.0)
        l1 = ((p - gt_crops).abs() * m).sum() / (3.0 * n)
        s = ssim(p, gt_crops, mask=mask_crops) if lambda_dssim > 0 else pred.new_tensor(1.0)
    return lambda_l1 * l1 + lambda_dssim * (1.0 - s), l1, s
