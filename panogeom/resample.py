"""Sampling an equirectangular image at continuous pixel positions or along directions, with
cv2.remap: columns are periodic (a sample between the last and the first column blends the two,
across the ±180° seam) and rows clamp at the poles. One rule for every resampling of a panorama
that is not differentiable (turned panoramas, perspective crops, edge votes); `panogeom.equirect.
sample_bilinear` is its exact float64 twin for a few points, and the trainer's torch resamplers
(gaussians/view_jitter.py, gaussians/crop_loss.py) follow the same rule."""

from __future__ import annotations

import cv2
import numpy as np

from panogeom.equirect import angles_to_pixel, dirs_to_angles

__all__ = ["remap_equirect", "sample_along", "perspective_crop"]

#: cv2.remap takes its maps as images, whose sides must stay below 32767: longer lists of samples are
#: folded into rows of this many
_FOLD = 1024


def remap_equirect(image: np.ndarray, col: np.ndarray, row: np.ndarray,
                   interpolation: int = cv2.INTER_LINEAR) -> np.ndarray:
    """`image` ([H,W] or [H,W,C]) sampled at continuous (col, row) (pixel centres at integers, any
    shape, the same for both): [*shape] or [*shape, C] in the image's dtype."""
    h, w = image.shape[:2]
    shape = np.shape(col)
    # one wrapped column on each side covers every column position modulo W
    padded = np.concatenate([image[:, -1:], image, image[:, :1]], axis=1)
    mx = np.mod(np.asarray(col, np.float64) + 0.5, w) - 0.5 + 1.0
    my = np.clip(np.asarray(row, np.float64), 0.0, h - 1.0)
    if len(shape) != 2 or max(shape) >= 32767:  # fold into rows of _FOLD samples
        n = int(np.prod(shape))
        rows = max(1, -(-n // _FOLD))
        mx = np.resize(mx.ravel(), rows * _FOLD).reshape(rows, _FOLD)
        my = np.resize(my.ravel(), rows * _FOLD).reshape(rows, _FOLD)
        out = cv2.remap(padded, mx.astype(np.float32), my.astype(np.float32), interpolation,
                        borderMode=cv2.BORDER_REPLICATE)
        return out.reshape(rows * _FOLD, *image.shape[2:])[:n].reshape(*shape, *image.shape[2:])
    return cv2.remap(padded, mx.astype(np.float32), my.astype(np.float32), interpolation,
                     borderMode=cv2.BORDER_REPLICATE)


def sample_along(image: np.ndarray, dirs: np.ndarray, interpolation: int = cv2.INTER_LINEAR) -> np.ndarray:
    """`image` sampled along camera-frame directions `dirs` [..., 3] (any length): [...] or [..., C]."""
    col, row = angles_to_pixel(*dirs_to_angles(np.asarray(dirs, np.float64)), *image.shape[:2])
    return remap_equirect(image, col, row, interpolation)


def perspective_crop(pano: np.ndarray, rotation: np.ndarray, camera) -> np.ndarray:
    """The perspective image of `camera` (a pinhole: fx, fy, cx, cy, width, height, as
    splatting.PinholeCamera) turned by `rotation` (world-to-crop, its rows the crop's axes in the
    panorama's frame) resampled from the panorama: the crops the perspective baseline trains on."""
    c, r = np.meshgrid(np.arange(int(camera.width)) + 0.5, np.arange(int(camera.height)) + 0.5)
    d_crop = np.stack([(c - camera.cx) / camera.fx, (r - camera.cy) / camera.fy, np.ones_like(c)], -1)
    return sample_along(pano, d_crop @ np.asarray(rotation, dtype=np.float64)[:3, :3])  # rotationᵀ d_crop
