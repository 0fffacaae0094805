"""The depth a layout implies: each ray cast against a view's metric room (floor y = +h, ceiling
y = -d, vertical walls on the floor polygon, all in the camera frame), with the surface it meets."""

from __future__ import annotations

import numpy as np

from panogeom.equirect import column_longitudes, row_latitudes
from panogeom.surfaces import CEILING, FLOOR, NONE, WALL


def _cross(a0, a1, b0, b1):
    return a0 * b1 - a1 * b0


def ray_polygon_distance(polygon_xz, ux: np.ndarray, uz: np.ndarray, chunk: int = 65536) -> np.ndarray:
    """Distance from the origin along 2D unit rays (ux, uz) [N] to the nearest polygon edge; inf on a miss."""
    poly = np.asarray(polygon_xz, dtype=np.float64).reshape(-1, 2)
    a = poly
    e = np.roll(poly, -1, axis=0) - poly  # edge k runs from a[k] to a[k] + e[k]
    ux = np.asarray(ux, dtype=np.float64).reshape(-1)
    uz = np.asarray(uz, dtype=np.float64).reshape(-1)
    out = np.full(ux.shape, np.inf)
    ae = _cross(a[:, 0], a[:, 1], e[:, 0], e[:, 1])  # [K]
    for s in range(0, len(ux), chunk):
        x, z = ux[s : s + chunk, None], uz[s : s + chunk, None]
        with np.errstate(divide="ignore", invalid="ignore"):
            den = _cross(x, z, e[None, :, 0], e[None, :, 1])
            t = ae[None] / den
            u = _cross(a[None, :, 0], a[None, :, 1], x, z) / den
        hit = (np.abs(den) > 1e-12) & (t > 1e-9) & (u >= -1e-9) & (u <= 1 + 1e-9)
        out[s : s + chunk] = np.where(hit, t, np.inf).min(axis=1)
    return out


def layout_depth(polygon_xz, camera_height: float, ceiling_distance: float, dirs: np.ndarray):
    """Distance along each ray to the layout room, and its label.

    `dirs` [...,3] are camera-frame directions (normalised here); the room is
    the floor polygon (x, z) extruded from the floor (y = +camera_height) to
    the ceiling (y = -ceiling_distance). Returns (depth [...] float64, inf on
    a miss; label [...] int8: WALL 0, FLOOR 1, CEILING 2, NONE -1).
    """
    d = np.asarray(dirs, dtype=np.float64)
    shape = d.shape[:-1]
    d = d.reshape(-1, 3)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    horiz = np.hypot(d[:, 0], d[:, 2])
    with np.errstate(divide="ignore", invalid="ignore"):
        rho = ray_polygon_distance(polygon_xz, d[:, 0] / horiz, d[:, 2] / horiz)
        t_wall = np.where(horiz > 1e-12, rho / horiz, np.inf)
        t_plane = np.where(
            d[:, 1] > 0, camera_height / d[:, 1], np.where(d[:, 1] < 0, -ceiling_distance / d[:, 1], np.inf)
        )
    return _combine(t_wall, t_plane, d[:, 1] > 0, shape)


def layout_depth_map(polygon_xz, camera_height: float, ceiling_distance: float, height: int, width: int):
    """`layout_depth` for every pixel of an H x W equirectangular image (walls cast once per column)."""
    phi = column_longitudes(width)
    theta = row_latitudes(height)
    rho = ray_polygon_distance(polygon_xz, np.sin(phi), np.cos(phi))  # [W] horizontal distance to the wall
    cos_t, sin_t = np.cos(theta)[:, None], np.sin(theta)[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        t_wall = rho[None, :] / cos_t
        # Unit direction y = -sin(theta): the floor (y = +h) below the horizon, the ceiling above it.
        t_plane = np.where(
            sin_t < 0, camera_height / -sin_t, np.where(sin_t > 0, ceiling_distance / sin_t, np.inf)
        )
    t_plane = np.broadcast_to(t_plane, (height, width))
    down = np.broadcast_to(sin_t < 0, (height, width))
    return _combine(np.broadcast_to(t_wall, (height, width)), t_plane, down, (height, width))


def _combine(t_wall, t_plane, down, shape):
    wall = t_wall <= t_plane
    depth = np.where(wall, t_wall, t_plane)
    label = np.where(wall, WALL, np.where(down, FLOOR, CEILING)).astype(np.int8)
    label[~np.isfinite(depth)] = NONE
    return depth.reshape(shape), label.reshape(shape)
