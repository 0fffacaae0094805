"""Equirectangular conventions of DESIGN.md, in one place.

Camera and world frames are OpenCV-style: x right, y down, z forward.
Longitude phi = atan2(x, z) in (-pi, pi], latitude theta = atan2(-y, hypot(x, z))
(up is positive). Pixel centres sit at +0.5:
    c = (phi / (2 pi) + 0.5) W - 0.5,    r = (0.5 - theta / pi) H - 0.5.

All functions accept numpy arrays and broadcast; they are small enough that the
torch code (splatting/) keeps its own copy rather than importing this module.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "angles_to_dirs",
    "dirs_to_angles",
    "pixel_to_angles",
    "angles_to_pixel",
    "pixel_grid_angles",
    "ray_directions",
    "column_longitudes",
    "row_latitudes",
    "project_to_pixels",
    "sample_bilinear",
]


def angles_to_dirs(phi: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Unit directions [...,3] for longitude phi and latitude theta (radians)."""
    phi = np.asarray(phi, dtype=np.float64)
    theta = np.asarray(theta, dtype=np.float64)
    cos_t = np.cos(theta)
    return np.stack([cos_t * np.sin(phi), -np.sin(theta), cos_t * np.cos(phi)], axis=-1)


def dirs_to_angles(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(phi, theta) of directions [...,3]; need not be unit length."""
    d = np.asarray(d, dtype=np.float64)
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    return np.arctan2(x, z), np.arctan2(-y, np.hypot(x, z))


def column_longitudes(width: int) -> np.ndarray:
    """Longitude of each column's centre, [W]."""
    return ((np.arange(width) + 0.5) / width - 0.5) * 2.0 * np.pi


def row_latitudes(height: int) -> np.ndarray:
    """Latitude of each row's centre, [H] (top row is near +pi/2)."""
    return (0.5 - (np.arange(height) + 0.5) / height) * np.pi


def pixel_to_angles(col: np.ndarray, row: np.ndarray, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Continuous pixel coordinates (centres at integers) to (phi, theta)."""
    phi = ((np.asarray(col, dtype=np.float64) + 0.5) / width - 0.5) * 2.0 * np.pi
    theta = (0.5 - (np.asarray(row, dtype=np.float64) + 0.5) / height) * np.pi
    return phi, theta


def angles_to_pixel(phi: np.ndarray, theta: np.ndarray, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """(phi, theta) to continuous (col, row), DESIGN.md's mapping."""
    col = (np.asarray(phi, dtype=np.float64) / (2.0 * np.pi) + 0.5) * width - 0.5
    row = (0.5 - np.asarray(theta, dtype=np.float64) / np.pi) * height - 0.5
    return col, row


def pixel_grid_angles(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """[H,W] longitude and latitude of every pixel centre."""
    phi, theta = np.meshgrid(column_longitudes(width), row_latitudes(height))
    return phi, theta


def ray_directions(height: int, width: int) -> np.ndarray:
    """[H,W,3] unit ray directions in the camera frame."""
    phi, theta = pixel_grid_angles(height, width)
    return angles_to_dirs(phi, theta)


def nadir_cap(height: int, width: int, radius_deg: float) -> np.ndarray:
    """[H,W] bool, True outside a cap of `radius_deg` around the nadir (the bottom of the image):
    the pixels a tripod or a hand at the nadir leaves valid. 0 masks nothing."""
    theta = row_latitudes(height)  # +pi/2 at the top row, -pi/2 at the bottom
    valid_rows = theta > -np.pi / 2 + np.deg2rad(radius_deg)
    return np.broadcast_to(valid_rows[:, None], (height, width)).copy()


def project_to_pixels(
    points: np.ndarray, pose: np.ndarray, height: int, width: int
) -> tuple[np.ndarray, np.ndarray]:
    """World points [N,3] -> continuous (col, row) in an H x W panorama with camera-to-world `pose`."""
    pose = np.asarray(pose, dtype=np.float64)
    cam = (points - pose[:3, 3]) @ pose[:3, :3]  # R^T (p - t)
    phi, theta = dirs_to_angles(cam)
    return angles_to_pixel(phi, theta, height, width)


def sample_bilinear(image: np.ndarray, col: np.ndarray, row: np.ndarray) -> np.ndarray:
    """Bilinear lookup [N,C] at continuous pixel coordinates (centres at integers); columns wrap
    around the longitude seam, rows clamp at the poles."""
    h, w = image.shape[:2]
    row = np.clip(row, 0.0, h - 1.0)
    c0 = np.floor(col)
    r0 = np.floor(row)
    fc = (col - c0)[:, None]
    fr = (row - r0)[:, None]
    c0 = c0.astype(np.int64) % w
    c1 = (c0 + 1) % w
    r0 = r0.astype(np.int64)
    r1 = np.minimum(r0 + 1, h - 1)
    top = image[r0, c0] * (1 - fc) + image[r0, c1] * fc
    bot = image[r1, c0] * (1 - fc) + image[r1, c1] * fc
    return top * (1 - fr) + bot * fr
