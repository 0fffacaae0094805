"""Analytic rooms for the layout tests: exact boundaries by shapely ray casting
(independent of layoutnet.postprocess.polygon_to_boundaries)."""

from __future__ import annotations

import numpy as np
from shapely.geometry import LineString, Point, Polygon


def columns_phi(width: int) -> np.ndarray:
    return ((np.arange(width) + 0.5) / width - 0.5) * 2 * np.pi


def exact_boundaries(
    polygon, camera_xz, camera_height: float, ceiling_height: float, width: int, yaw: float = 0.0
) -> np.ndarray:
    """[2,W] latitudes of the ceiling-wall and floor-wall edges of an extruded
    floor plan (world x,z), seen from a level camera at camera_xz whose
    forward axis is turned by `yaw` (world = R_y(yaw) camera, like
    tests/conftest.py's yaw_pose)."""
    poly = Polygon(polygon)
    cam = np.asarray(camera_xz, dtype=float)
    far = 100.0
    out = np.empty((2, width))
    for i, phi in enumerate(columns_phi(width)):
        # camera-frame direction (sin phi, cos phi) in (x,z), rotated to world by yaw about y
        dx, dz = np.sin(phi), np.cos(phi)
        c, s = np.cos(yaw), np.sin(yaw)
        wx, wz = c * dx + s * dz, -s * dx + c * dz
        ray = LineString([tuple(cam), (cam[0] + far * wx, cam[1] + far * wz)])
        hit = ray.intersection(poly.exterior)
        pts = [hit] if hit.geom_type == "Point" else list(getattr(hit, "geoms", []))
        d = min(Point(cam).distance(p) for p in pts)
        out[0, i] = np.arctan2(ceiling_height - camera_height, d)
        out[1, i] = -np.arctan2(camera_height, d)
    return out


def world_to_camera_xz(points, camera_xz, yaw: float = 0.0) -> np.ndarray:
    """World (x,z) points into the camera's (x,z) frame (inverse of the yaw rotation)."""
    p = np.asarray(points, dtype=float) - np.asarray(camera_xz, dtype=float)
    c, s = np.cos(yaw), np.sin(yaw)
    # camera = R^T world, R = [[c, s], [-s, c]] acting on (x, z)
    return np.stack([c * p[:, 0] - s * p[:, 1], s * p[:, 0] + c * p[:, 1]], axis=1)


def match_corners(pred, true) -> float:
    """Max distance from each true corner to its nearest predicted corner (and
    the same count is required by the caller)."""
    pred = np.asarray(pred, dtype=float)
    true = np.asarray(true, dtype=float)
    d = np.linalg.norm(true[:, None, :] - pred[None, :, :], axis=2)
    return float(max(d.min(axis=1).max(), d.min(axis=0).max()))


L_SHAPE = [(-2.0, -1.5), (3.0, -1.5), (3.0, 1.0), (0.5, 1.0), (0.5, 2.5), (-2.0, 2.5)]
CUBOID = [(-1.7, -2.2), (2.4, -2.2), (2.4, 1.9), (-1.7, 1.9)]


def pose_world_to_camera_xz(points, pose) -> np.ndarray:
    """World (x, z) floor points into a camera's (x, z), from its camera-to-world 4x4 pose."""
    m = np.asarray(pose, dtype=float)
    p = np.asarray(points, dtype=float)
    rel = np.zeros((len(p), 3))
    rel[:, 0] = p[:, 0] - m[0, 3]
    rel[:, 2] = p[:, 1] - m[2, 3]
    cam = rel @ m[:3, :3]  # R^T rel, row-wise
    return cam[:, [0, 2]]


def yaw_pose(yaw: float, position) -> list[list[float]]:
    c, s = np.cos(yaw), np.sin(yaw)
    m = np.eye(4)
    m[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    m[:3, 3] = position
    return m.tolist()


def json_corners_xz(data: dict, width: int, height: int, camera_height: float) -> np.ndarray:
    """Metric camera-frame corners a HorizonNet JSON implies (its floor points at the
    given camera height), straight from HorizonNet's formulas: u = coorx2u(u W),
    v = coory2v(v H), distance = h / tan(-v_floor)."""
    uv = np.asarray(data["uv"], dtype=float).reshape(-1, 2, 2)
    u = ((uv[:, 1, 0] * width + 0.5) / width - 0.5) * 2 * np.pi
    v = -((uv[:, 1, 1] * height + 0.5) / height - 0.5) * np.pi
    d = camera_height / np.tan(-v)
    return np.stack([d * np.sin(u), d * np.cos(u)], axis=1)


def run_layout(scene_root, out_dir, **params):
    """Run the layout stage's `run` on a scene folder; returns (output, warnings)."""
    from schemas.scene_loader import load_scene
    from runtime.stage import StageContext
    from stages import layout

    out_dir.mkdir(parents=True, exist_ok=True)
    ctx = StageContext(
        scene=load_scene(scene_root), params=layout.Params(**params), inputs={}, out_dir=out_dir
    )
    out = layout.run(ctx)
    return out, ctx.warnings
