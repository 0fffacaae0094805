"""Depth maps as world points: back-projection, a scale-only ICP against the layout cloud (the
scale acts about each camera centre because the poses are fixed; a similarity ICP would move the
cameras), and open3d's voxel and outlier filtering of the merged cloud."""

from __future__ import annotations

import numpy as np

from panogeom.equirect import angles_to_dirs, column_longitudes, row_latitudes


def view_rays(depth: np.ndarray, pose: np.ndarray, stride: int = 1):
    """World-frame ray vectors r (camera centre c + r is the surface point) of the valid pixels.

    Returns (r [N,3] float64, flat pixel indices [N] into the strided grid, c [3]).
    """
    h, w = depth.shape
    theta = row_latitudes(h)[::stride]
    phi = column_longitudes(w)[::stride]
    dsub = depth[::stride, ::stride]
    pp, tt = np.meshgrid(phi, theta)
    valid = np.isfinite(dsub) & (dsub > 0)
    idx = np.flatnonzero(valid)
    dirs = angles_to_dirs(pp.reshape(-1)[idx], tt.reshape(-1)[idx])
    pose = np.asarray(pose, dtype=np.float64)
    r = (dirs * dsub.reshape(-1)[idx, None]) @ pose[:3, :3].T
    return r, idx, pose[:3, 3].copy()


def refine_scale_icp(
    centres: np.ndarray,
    rays: np.ndarray,
    layout_points: np.ndarray,
    layout_normals: np.ndarray | None,
    *,
    max_distance: float,
    iterations: int,
) -> tuple[float, dict]:
    """Scale-only ICP: the factor lam minimising the point-to-plane distances of c + lam*r to the layout.

    `centres` [N,3] (each point's camera centre) and `rays` [N,3]. Correspondences
    are nearest layout points (scipy cKDTree) within `max_distance`; with zero
    or missing normals the point-to-point closed form is used.
    """
    from scipy.spatial import cKDTree

    lp = np.asarray(layout_points, dtype=np.float64)
    ln = None if layout_normals is None else np.asarray(layout_normals, dtype=np.float64)
    plane = ln is not None and np.all(np.linalg.norm(ln, axis=1) > 0.5)
    tree = cKDTree(lp)
    lam = 1.0
    used = 0
    for _ in range(iterations):
        p = centres + lam * rays
        dist, idx = tree.query(p, k=1, distance_upper_bound=max_distance)
        ok = np.isfinite(dist)
        used = int(ok.sum())
        if used < 10:
            return 1.0, {"correspondences": used, "converged": False}
        r, c, q = rays[ok], centres[ok], lp[idx[ok]]
        if plane:
            nn = ln[idx[ok]]
            a = np.einsum("ij,ij->i", nn, r)
            b = np.einsum("ij,ij->i", nn, q - c)
            # Trim to 3 robust sigmas of the point-to-plane residuals (clutter near the walls).
            res = np.abs(a * lam - b)
            keep = res < max(3 * 1.4826 * float(np.median(res)), 1e-3)
            if keep.sum() >= 10:
                a, b = a[keep], b[keep]
        else:
            a, b = r, q - c
            a, b = a.reshape(-1), b.reshape(-1)
        new = float(np.dot(a, b) / np.dot(a, a))
        if abs(new - lam) < 1e-6 * abs(lam):
            lam = new
            break
        lam = new
    p = centres + lam * rays
    dist, idx = tree.query(p, k=1, distance_upper_bound=max_distance)
    ok = np.isfinite(dist)
    if plane and ok.any():  # the distance to the layout surface, not to its nearest sample
        dist[ok] = np.abs(np.einsum("ij,ij->i", ln[idx[ok]], p[ok] - lp[idx[ok]]))
    stats = {
        "correspondences": int(ok.sum()),
        "fitness": float(ok.mean()) if len(ok) else 0.0,
        "rmse_m": float(np.sqrt(np.mean(dist[ok] ** 2))) if ok.any() else float("nan"),
        "converged": True,
    }
    return lam, stats


def merge_points(
    points: np.ndarray,
    colors: np.ndarray,
    *,
    voxel_size: float,
    nb_neighbors: int,
    std_ratio: float,
) -> tuple[np.ndarray, np.ndarray]:
    """open3d voxel_down_sample (colours averaged; 0 = off) then remove_statistical_outlier
    (`nb_neighbors` 0 = off)."""
    import open3d as o3d

    pc = o3d.geometry.PointCloud()
    pc.points = o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64))
    pc.colors = o3d.utility.Vector3dVector(np.clip(np.asarray(colors, dtype=np.float64), 0, 1))
    if voxel_size > 0:
        pc = pc.voxel_down_sample(voxel_size)
    if nb_neighbors > 0 and len(pc.points) > nb_neighbors:
        pc, _ = pc.remove_statistical_outlier(nb_neighbors=nb_neighbors, std_ratio=std_ratio)
    return np.asarray(pc.points, dtype=np.float32), np.asarray(pc.colors, dtype=np.float32)
