"""Rotating equirectangular panoramas and the rotations between camera frames.

`rotate_equirect(image, R)` turns the panorama's content by R: what was seen
along direction d is seen along R d afterwards (out(d) = image(Rᵀ d)).
"""

from __future__ import annotations

import cv2
import numpy as np

from panogeom.equirect import ray_directions
from panogeom.resample import sample_along

__all__ = ["rotate_equirect", "yaw_matrix", "level_rotation", "yaw_tilt_deg"]


def yaw_matrix(yaw: float) -> np.ndarray:
    """Rotation by `yaw` radians about +y (adds yaw to every longitude)."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def level_rotation(down: np.ndarray) -> np.ndarray:
    """The smallest rotation taking a camera frame's gravity direction `down` to +y (level), no yaw."""
    from scipy.spatial.transform import Rotation

    down = np.asarray(down, dtype=np.float64)
    # one vector pair: scipy returns the minimal rotation between them
    return Rotation.align_vectors([[0.0, 1.0, 0.0]], [down / np.linalg.norm(down)])[0].as_matrix()


def yaw_tilt_deg(rotation: np.ndarray) -> tuple[float, float]:
    """(yaw, tilt) in degrees of R = yaw_matrix(yaw) @ level_rotation(Rᵀ ŷ): tilt is the angle between
    the frame's down axis and gravity, yaw the turn about gravity that is left."""
    R = np.asarray(rotation, dtype=np.float64)
    down = R.T @ np.array([0.0, 1.0, 0.0])
    tilt = float(np.degrees(np.arccos(np.clip(down[1], -1.0, 1.0))))
    Y = R @ level_rotation(down).T
    return float(np.degrees(np.arctan2(Y[0, 2], Y[0, 0]))), tilt


def rotate_equirect(image: np.ndarray, rotation: np.ndarray, size: tuple[int, int] | None = None,
                    interpolation: int = cv2.INTER_LINEAR) -> np.ndarray:
    """The panorama turned by `rotation` (out(d) = image(Rᵀ d)), at `size` (H, W; default the input's).
    Bilinear, periodic across the ±180° seam; a rotation about +y by a multiple of the pixel
    pitch is an exact column roll."""
    h, w = size or image.shape[:2]
    return sample_along(image, ray_directions(h, w) @ np.asarray(rotation, dtype=np.float64), interpolation)  # Rᵀ d
