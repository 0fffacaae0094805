"""Initialising Gaussians from a point cloud (layout / depth) or at random.

Point-cloud init follows 3DGS: colour -> SH degree 0, scale = mean distance to
the 3 nearest neighbours (isotropic), opacity 0.1, identity rotation. Layout
points (which lie on a known plane) are flattened: their local z axis is
turned onto the plane normal and its scale shrunk by `layout_flatten`, so the
Gaussian starts as a disc in the wall/floor/ceiling it came from.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
from scipy.spatial import cKDTree

from gaussians.model import Gaussians, rgb_to_sh

__all__ = [
    "knn_mean_distance",
    "rotation_to_quat",
    "quat_with_z_along",
    "from_cloud",
    "random_points",
    "random_in_rooms",
    "random_around_cameras",
    "MIN_SCALE",
]

#: Floor for initial scales (duplicate points have a zero neighbour distance).
MIN_SCALE = 1e-4


def knn_mean_distance(points: np.ndarray, k: int = 3) -> np.ndarray:
    """Mean Euclidean distance of each point to its `k` nearest other points, [N]."""
    pts = np.asarray(points, dtype=np.float64)
    n = pts.shape[0]
    if n == 0:
        return np.zeros(0)
    if n == 1:
        return np.full(1, 0.01)
    kk = min(k, n - 1)
    dist, _ = cKDTree(pts).query(pts, k=kk + 1)  # first neighbour is the point itself
    return dist[:, 1:].mean(axis=1)


def rotation_to_quat(r: np.ndarray) -> np.ndarray:
    """Rotation matrices [...,3,3] -> unit quaternions [...,4] (w, x, y, z), w >= 0."""
    r = np.asarray(r, dtype=np.float64)
    m00, m11, m22 = r[..., 0, 0], r[..., 1, 1], r[..., 2, 2]
    # Four candidate forms; pick per matrix the one with the largest (stable) pivot.
    cand = np.stack(
        [
            np.stack([1 + m00 + m11 + m22, r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0],
                      r[..., 1, 0] - r[..., 0, 1]], -1),
            np.stack([r[..., 2, 1] - r[..., 1, 2], 1 + m00 - m11 - m22, r[..., 0, 1] + r[..., 1, 0],
                      r[..., 0, 2] + r[..., 2, 0]], -1),
            np.stack([r[..., 0, 2] - r[..., 2, 0], r[..., 0, 1] + r[..., 1, 0], 1 - m00 + m11 - m22,
                      r[..., 1, 2] + r[..., 2, 1]], -1),
            np.stack([r[..., 1, 0] - r[..., 0, 1], r[..., 0, 2] + r[..., 2, 0], r[..., 1, 2] + r[..., 2, 1],
                      1 - m00 - m11 + m22], -1),
        ],
        axis=-2,
    )
    pivots = np.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1)
    best = np.argmax(pivots, axis=-1)
    q = np.take_along_axis(cand, best[..., None, None], axis=-2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0, -q, q)


def quat_with_z_along(normals: np.ndarray) -> np.ndarray:
    """Quaternions whose rotation maps the local z axis onto each (unit) normal, [N,4]."""
    n = np.asarray(normals, dtype=np.float64)
    n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    # A helper axis not parallel to n, then Gram-Schmidt: R = [t1 t2 n].
    helper = np.where(np.abs(n[:, 1:2]) < 0.9, np.array([[0.0, 1.0, 0.0]]), np.array([[1.0, 0.0, 0.0]]))
    t1 = np.cross(helper, n)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(n, t1)
    r = np.stack([t1, t2, n], axis=-1)  # columns
    return rotation_to_quat(r)


def from_cloud(
    cloud: dict[str, np.ndarray],
    sh_degree: int = 3,
    init_opacity: float = 0.1,
    layout_flatten: float = 0.1,
    dtype=torch.float32,
) -> Gaussians:
    """Gaussians at the points of a cloud (stages/cloud_io.read_cloud's dict)."""
    pts = np.asarray(cloud["points"], dtype=np.float64)
    n = pts.shape[0]
    colors = np.clip(np.asarray(cloud.get("colors", np.full((n, 3), 0.5)), dtype=np.float64), 0, 1)
    normals = np.asarray(cloud.get("normals", np.zeros((n, 3))), dtype=np.float64)
    u0 = np.asarray(cloud.get("u0", pts), dtype=np.float64)
    is_layout = np.asarray(cloud.get("is_layout", np.zeros(n, bool)), dtype=bool)
    nlen = np.linalg.norm(normals, axis=1)
    # A layout point without a usable normal cannot be regularised: treat it as a plain point.
    is_layout = is_layout & (nlen > 0.5)

    scale = np.maximum(knn_mean_distance(pts), MIN_SCALE)
    log_scales = np.repeat(np.log(scale)[:, None], 3, axis=1)
    quats = np.tile(np.array([1.0, 0.0, 0.0, 0.0]), (n, 1))
    if is_layout.any():
        quats[is_layout] = quat_with_z_along(normals[is_layout])
        log_scales[is_layout, 2] += math.log(layout_flatten)
        unit = normals[is_layout] / nlen[is_layout, None]
        normals = normals.copy()
        normals[is_layout] = unit
    logit = math.log(init_opacity / (1.0 - init_opacity))
    k = (sh_degree + 1) ** 2

    def t(a):
        return torch.as_tensor(np.ascontiguousarray(a), dtype=dtype)

    return Gaussians(
        means=t(pts),
        quats=t(quats),
        log_scales=t(log_scales),
        opacity_logits=torch.full((n,), logit, dtype=dtype),
        sh_dc=rgb_to_sh(t(colors)).reshape(n, 1, 3),
        sh_rest=torch.zeros((n, k - 1, 3), dtype=dtype),
        is_layout=torch.as_tensor(is_layout),
        normals=t(np.where(is_layout[:, None], normals, 0.0)),
        u0=t(u0),
    )


def random_in_rooms(rooms: Sequence, count: int, rng: np.random.Generator) -> np.ndarray:
    """`count` points uniform inside the union's rooms (floor polygons extruded floor to ceiling).

    `rooms` are schemas.union.Room (or dicts with polygon/holes/floor_y/ceiling_y).
    """
    import shapely

    polys, heights = [], []
    for room in rooms:
        r = room if isinstance(room, dict) else room.model_dump()
        poly = shapely.Polygon(r["polygon"], r.get("holes") or [])
        polys.append((poly, float(r["ceiling_y"]), float(r["floor_y"])))
        heights.append(poly.area * abs(float(r["floor_y"]) - float(r["ceiling_y"])))
    vol = np.asarray(heights, dtype=np.float64)
    if len(polys) == 0 or not np.all(np.isfinite(vol)) or vol.sum() <= 0:
        raise ValueError("rooms have no volume")
    per_room = rng.multinomial(count, vol / vol.sum())
    out = []
    for (poly, y0, y1), m in zip(polys, per_room):
        x0, z0, x1, z1 = poly.bounds
        got: list[np.ndarray] = []
        have = 0
        while have < m:  # rejection sampling inside the polygon
            cand = rng.uniform([x0, z0], [x1, z1], size=(max(2 * (m - have), 16), 2))
            keep = cand[shapely.contains_xy(poly, cand[:, 0], cand[:, 1])]
            got.append(keep)
            have += len(keep)
        xz = np.concatenate(got)[:m]
        y = rng.uniform(min(y0, y1), max(y0, y1), size=m)
        out.append(np.stack([xz[:, 0], y, xz[:, 1]], axis=1))
    return np.concatenate(out, axis=0)


def random_around_cameras(
    positions: np.ndarray, count: int, rng: np.random.Generator, margin: float = 3.0, vertical: float = 1.5
) -> np.ndarray:
    """`count` points uniform in the cameras' bounding box grown by `margin` m
    horizontally (x, z) and `vertical` m up and down (y)."""
    p = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    grow = np.array([margin, vertical, margin])
    return rng.uniform(p.min(0) - grow, p.max(0) + grow, size=(count, 3))


def random_points(
    count: int,
    seed: int,
    rooms: Sequence | None = None,
    camera_positions: np.ndarray | None = None,
    sh_degree: int = 3,
    init_opacity: float = 0.1,
    dtype=torch.float32,
) -> Gaussians:
    """The paper's "3D-GS*" baseline: Gaussians at uniform random points with random colours."""
    rng = np.random.default_rng(seed)
    if rooms:
        pts = random_in_rooms(rooms, count, rng)
    elif camera_positions is not None:
        pts = random_around_cameras(camera_positions, count, rng)
    else:
        raise ValueError("random initialisation needs rooms or camera positions for its bounds")
    colors = rng.uniform(0.0, 1.0, size=(count, 3))
    return from_cloud({"points": pts, "colors": colors}, sh_degree=sh_degree, init_opacity=init_opacity,
                      dtype=dtype)
