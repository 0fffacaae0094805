"""align: per-view depth scaled to the layout, back-projected, merged and joined with the layout cloud.

1. The depth the layout implies: every pixel's ray is cast against the view's
   metric room (floor y = +h, ceiling y = -d, vertical walls on the floor
   polygon, all in the camera frame) -> layout depth and a wall/floor/ceiling
   label (`layout_depth`, `layout_depth_map`).
2. A robust fit of the depth to the layout depth, robust to furniture and
   noise: RANSAC on minimal samples, least squares on the inliers (relative
   error below `inlier_threshold`), then IRLS with Tukey's biweight. The
   model of depth decides the unknowns and the groups: metric distance, one
   scale for all views (the paper's global factor); affine depth, scale and
   shift; affine inverse depth (Depth Anything), scale and shift in inverse
   depth, 1/d = s*v + t, per view (`fit_scale`).
3. Refinement against the layout cloud by a scale-only point-to-plane ICP
   (`refine_scale_icp`): the scale acts about each camera centre because the
   poses are fixed; a similarity ICP would move the cameras.
4. Merge with open3d: voxel_down_sample, remove_statistical_outlier; the layout
   points from `sampling` are appended with their normals and u0.

Without a layout the (metric) depth is used as it is, scale 1: the paper's
"depth" initialisation. See docs/depth.md.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field

from panogeom.equirect import angles_to_dirs, column_longitudes, row_latitudes
from panogeom.surfaces import CEILING, FLOOR, NONE, SURFACE_NAMES, WALL
from runfs.errors import PanoError
from runfs.limits import load_npy
from schemas.scene_loader import valid_mask
from runtime.stage import StageContext
from schemas.align import AlignOutput, KindFit
from schemas.depth import DEPTH_MODELS
from schemas.scene import Scene
from schemas.stage_params import StageParams

Output = AlignOutput

Kind = Literal["metric", "relative", "disparity"]
LABELS = {name: k for k, name in enumerate(SURFACE_NAMES)}
EQUATIONS = {"metric": "d = s*v", "relative": "d = s*v + t", "disparity": "1/d = s*v + t"}


class Params(StageParams):
    inlier_threshold: float = Field(
        default=0.1,
        gt=0,
        lt=1,
        description="A pixel agrees with the layout when |depth/layout - 1| is below this.",
    )
    min_inlier_share: float = Field(
        default=0.3, ge=0, le=1, description="Refuse the fit when fewer of the labelled pixels agree."
    )
    min_pixels: int = Field(default=200, ge=2, description="Refuse when fewer valid labelled pixels exist.")
    labels: list[Literal["wall", "floor", "ceiling"]] = Field(
        default=["wall", "floor", "ceiling"], min_length=1, description="Layout surfaces the fit uses."
    )
    max_fit_pixels: int = Field(default=200_000, ge=100, description="Random subsample for the robust fit.")
    ransac_iterations: int = Field(
        default=256, ge=1, description="RANSAC hypotheses of the depth-to-layout scale fit.")
    icp: bool = Field(default=True, description="Refine the scale by ICP against the layout cloud.")
    icp_max_distance: float = Field(default=0.1, gt=0, description="ICP correspondence distance (m).")
    icp_iterations: int = Field(default=30, ge=1, description="ICP iterations at most (icp on).")
    icp_max_points: int = Field(
        default=50_000, ge=100, description="Random subsample of depth points for ICP."
    )
    icp_max_change: float = Field(
        default=0.1, gt=0, description="Reject (warn) an ICP scale change larger than this fraction."
    )
    stride: int = Field(default=1, ge=1, description="Back-project every stride-th pixel in each direction.")
    voxel_size: float = Field(default=0.02, ge=0, description="open3d voxel_down_sample size (m); 0 = off.")
    outlier_neighbors: int = Field(
        default=20, ge=0, description="remove_statistical_outlier nb_neighbors; 0 = off."
    )
    outlier_std_ratio: float = Field(
        default=2.0, gt=0,
        description="remove_statistical_outlier std_ratio: drop points whose mean neighbour distance "
                    "exceeds the average by this many standard deviations.")
    affine_fit: Literal["per_view", "global"] = Field(
        default="per_view",
        description="Relative depth / disparity: a scale and shift per view (models normalise each image) "
        "or one for all views.",
    )
    include_layout_points: bool = Field(default=True, description="Append the sampling stage's layout cloud.")
    seed: int = Field(default=0, ge=0, le=2**32 - 1, description="Random seed of RANSAC and the subsamples.")


def skip_reason(scene: Scene, params: Params) -> str | None:
    return None  # runs whenever its required input (depth) exists


# ----------------------------------------------------------------------------- layout depth (pure)


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


# ----------------------------------------------------------------------------- scale fit (pure)


@dataclass
class ScaleFit:
    kind: str
    scale: float
    shift: float
    inlier_share: float
    residual_m: float
    num_pixels: int

    def apply(self, values: np.ndarray) -> np.ndarray:
        return values_to_depth(values, self.kind, self.scale, self.shift)


def values_to_depth(values: np.ndarray, kind: str, scale: float = 1.0, shift: float = 0.0) -> np.ndarray:
    """Metres along the ray from a depth stage map; NaN where invalid (or non-positive)."""
    v = np.asarray(values, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        if kind == "metric":
            d = scale * v
        elif kind == "relative":
            d = scale * v + shift
        elif kind == "disparity":
            d = 1.0 / (scale * v + shift)
        else:
            raise ValueError(f"unknown depth kind {kind!r}")
    return np.where(np.isfinite(d) & (d > 0), d, np.nan)


def _design(v: np.ndarray, target: np.ndarray, kind: str):
    """Linear model x @ beta ~ y with weights w that make w * residual a relative depth error."""
    if kind == "metric":
        return v[:, None], target, 1.0 / target
    if kind == "relative":
        return np.stack([v, np.ones_like(v)], 1), target, 1.0 / target
    if kind == "disparity":  # 1/D ~ s v + t; D * (s v + t - 1/D) ~ the relative depth error
        return np.stack([v, np.ones_like(v)], 1), 1.0 / target, target
    raise ValueError(f"unknown depth kind {kind!r}")


TUKEY_C = 4.685  # Tukey biweight tuning constant: 95 % efficiency under Gaussian noise


def _irls_tukey(x, y, w, beta, threshold: float, m: int, iterations: int = 50) -> np.ndarray:
    """Iteratively reweighted least squares with Tukey's biweight on the relative residuals
    w*(x@beta - y), from `beta`. The residual scale is 1.4826*MAD of the residuals within
    `threshold`, re-estimated each iteration; the cut-off c = 4.685*scale never exceeds `threshold`.
    Pixels beyond c get weight 0 (furniture, clutter), those near 0 weight ~1."""
    for _ in range(iterations):
        r = w * (x @ beta - y)
        near = np.abs(r) < threshold
        if near.sum() <= 10 * m:
            break
        sigma = 1.4826 * float(np.median(np.abs(r[near])))
        c = min(threshold, max(TUKEY_C * sigma, 1e-6))
        u = r / c
        tw = np.where(np.abs(u) < 1, (1 - u * u) ** 2, 0.0)
        sw = w * np.sqrt(tw)
        if (tw > 0).sum() <= 10 * m:
            break
        new, *_ = np.linalg.lstsq(x * sw[:, None], y * sw, rcond=None)
        done = np.all(np.abs(new - beta) <= 1e-10 + 1e-8 * np.abs(beta))
        beta = new
        if done:
            break
    return beta


def fit_scale(
    values: np.ndarray,
    layout: np.ndarray,
    kind: str,
    inlier_threshold: float = 0.1,
    min_inlier_share: float = 0.3,
    min_pixels: int = 200,
    ransac_iterations: int = 256,
    max_pixels: int = 200_000,
    seed: int = 0,
    where: str | Path | None = "align",
) -> ScaleFit:
    """Robustly fit depth/disparity `values` to `layout` depth (metres) on pixels where both are valid.

    RANSAC over minimal samples scores hypotheses by the share of pixels whose
    relative depth error is below `inlier_threshold`; the best is refined by
    weighted least squares on its inliers until the inlier set settles, then
    by IRLS with Tukey's biweight (`_irls_tukey`). Metric: d = s*v; relative:
    d = s*v + t; disparity: 1/d = s*v + t (scale and shift in inverse depth).
    Raises PanoError when too few pixels exist or agree.
    """
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    D = np.asarray(layout, dtype=np.float64).reshape(-1)
    ok = np.isfinite(v) & np.isfinite(D) & (D > 0)
    if kind != "relative":
        ok &= v > 0  # metric depth and disparity are positive where valid
    v, D = v[ok], D[ok]
    n = len(v)
    if n < min_pixels:
        raise PanoError(
            where, f"only {n} valid depth pixels on the layout's walls/floor/ceiling (need {min_pixels})"
        )
    rng = np.random.default_rng(seed)
    if n > max_pixels:
        sel = rng.choice(n, max_pixels, replace=False)
        v, D = v[sel], D[sel]
        n = max_pixels
    x, y, w = _design(v, D, kind)
    m = x.shape[1]

    # RANSAC: hypotheses from minimal samples, scored on a fixed subset.
    score_idx = rng.choice(n, min(n, 20_000), replace=False)
    xs, ys, ws = x[score_idx], y[score_idx], w[score_idx]
    samples = rng.integers(0, n, size=(ransac_iterations, m))
    A = x[samples]  # [I,m,m]
    b = y[samples]  # [I,m]
    if m == 1:
        beta = (b / A[..., 0])[:, :1]
    else:
        det = A[:, 0, 0] * A[:, 1, 1] - A[:, 0, 1] * A[:, 1, 0]
        good = np.abs(det) > 1e-12 * (np.abs(A[:, :, 0]).max(1) + 1e-30)
        det = np.where(good, det, 1.0)
        s = (b[:, 0] * A[:, 1, 1] - b[:, 1] * A[:, 0, 1]) / det
        t = (A[:, 0, 0] * b[:, 1] - A[:, 1, 0] * b[:, 0]) / det
        beta = np.stack([np.where(good, s, np.nan), np.where(good, t, np.nan)], 1)
    err = np.abs(ws[None] * (beta @ xs.T - ys[None]))  # [I,S]
    counts = np.where(np.isfinite(err), err < inlier_threshold, False).sum(1)
    best = beta[int(np.argmax(counts))]

    # Refinement: weighted least squares on the inliers until they stop changing.
    inl = np.abs(w * (x @ best - y)) < inlier_threshold
    for _ in range(30):
        if inl.sum() < m:
            break
        sw = w[inl][:, None]
        best_new, *_ = np.linalg.lstsq(x[inl] * sw, y[inl] * w[inl], rcond=None)
        inl_new = np.abs(w * (x @ best_new - y)) < inlier_threshold
        best = best_new
        if np.array_equal(inl_new, inl):
            break
        inl = inl_new
    share = float(inl.mean()) if n else 0.0
    # Then Tukey's biweight by IRLS from there: clutter within the user threshold (furniture against
    # a wall) weighs less the further it lies, and clean pixels are not cut off at a hard edge.
    best = _irls_tukey(x, y, w, best, inlier_threshold, m)
    inl = np.abs(w * (x @ best - y)) < inlier_threshold
    share = float(inl.mean()) if n else 0.0
    scale = float(best[0])
    shift = float(best[1]) if m == 2 else 0.0
    if share < min_inlier_share or not np.isfinite(scale):
        raise PanoError(
            where,
            f"depth does not agree with the layout: {share:.0%} of {n} pixels within "
            f"{inlier_threshold:.0%} after fitting ({kind}), need {min_inlier_share:.0%}",
        )
    pred = values_to_depth(v[inl], kind, scale, shift)
    residual = float(np.nanmedian(np.abs(pred - D[inl]))) if inl.any() else float("nan")
    return ScaleFit(kind, scale, shift, share, residual, n)


# ----------------------------------------------------------------------------- geometry (pure)


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
    max_distance: float = 0.1,
    iterations: int = 30,
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
    voxel_size: float = 0.02,
    nb_neighbors: int = 20,
    std_ratio: float = 2.0,
) -> tuple[np.ndarray, np.ndarray]:
    """open3d voxel_down_sample (colours averaged) then remove_statistical_outlier."""
    import open3d as o3d

    pc = o3d.geometry.PointCloud()
    pc.points = o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64))
    pc.colors = o3d.utility.Vector3dVector(np.clip(np.asarray(colors, dtype=np.float64), 0, 1))
    if voxel_size > 0:
        pc = pc.voxel_down_sample(voxel_size)
    if nb_neighbors > 0 and len(pc.points) > nb_neighbors:
        pc, _ = pc.remove_statistical_outlier(nb_neighbors=nb_neighbors, std_ratio=std_ratio)
    return np.asarray(pc.points, dtype=np.float32), np.asarray(pc.colors, dtype=np.float32)


# ----------------------------------------------------------------------------- stage glue


def _with_factor(fit: ScaleFit, lam: float) -> tuple[float, float]:
    """(scale, shift) that give `lam` times the fitted depth through `values_to_depth`."""
    if fit.kind == "disparity":
        return fit.scale / lam, fit.shift / lam
    return fit.scale * lam, fit.shift * lam


@dataclass
class _ViewData:
    name: str
    kind: str
    values: np.ndarray  # [H,W] as the depth stage stored it
    pose: np.ndarray
    image: Path
    path: Path
    layout: np.ndarray | None = None  # [H,W] layout depth, NaN off the chosen labels


def run(ctx: StageContext[Params]) -> AlignOutput:
    from panogeom.images import read_rgb
    from stages.cloud_io import read_cloud, write_cloud

    p = ctx.params
    depth_in = ctx.inputs["depth"]
    layout_in = ctx.input("layout")
    sampling_in = ctx.input("sampling")
    wanted = np.array([LABELS[name] for name in p.labels])

    views: list[_ViewData] = []
    for vd in depth_in.data.views:
        path = depth_in.path(vd.depth)
        values = load_npy(path, pixels=True).astype(np.float32, copy=False)
        if values.ndim != 2:
            raise PanoError(path, f"expected an [H,W] depth map, got shape {list(values.shape)}")
        view = ctx.scene.manifest.view(vd.view)
        mask = valid_mask(ctx.scene, view, *values.shape)
        if mask is not None:  # a tripod or hand: neither fitted nor back-projected
            values = np.where(mask, values, np.nan).astype(np.float32)
        views.append(_ViewData(vd.view, vd.kind, values, view.pose_matrix, ctx.scene.image_path(view), path))

    layout_views = {}
    if layout_in is not None:
        layout_views = {lv.view: lv for lv in layout_in.data.views}
    for v in views:
        lv = layout_views.get(v.name)
        if lv is None:
            continue
        h, w = v.values.shape
        ld, lab = layout_depth_map(lv.floor_polygon, lv.camera_height, lv.ceiling_distance, h, w)
        v.layout = np.where(np.isin(lab, wanted), ld, np.nan).astype(np.float32)
    if layout_in is not None and not any(v.layout is not None for v in views):
        ctx.warn("no depth view has a layout: the depth is used as it is (scale 1)")

    # Relative depth without a layout cannot be placed: leave such views out while others remain
    # (a view the layout stage could not read), refuse below when none would.
    unplaced = [v for v in views if v.kind != "metric" and v.layout is None]
    if unplaced and len(unplaced) < len(views):
        ctx.warn(
            f"view(s) {', '.join(v.name for v in unplaced)}: {DEPTH_MODELS[unplaced[0].kind]} without a "
            "layout to fix its scale and shift; left out of the cloud"
        )
        views = [v for v in views if v not in unplaced]

    # Fit groups: all metric views share one scale (the paper's single global
    # factor); a relative or disparity model normalises each image on its own
    # (Depth Anything), so by default each such view gets its own scale and shift.
    groups: dict[str, list[_ViewData]] = {}
    for v in views:
        key = v.kind if v.kind == "metric" or p.affine_fit == "global" else f"{v.kind}:{v.name}"
        groups.setdefault(key, []).append(v)
    fits: dict[str, ScaleFit] = {}
    for key, group in groups.items():
        kind = group[0].kind
        with_layout = [v for v in group if v.layout is not None]
        if kind != "metric" and len(with_layout) < len(group):
            missing = next(v for v in group if v.layout is None)
            raise PanoError(
                missing.path,
                f"{kind} depth needs a layout to fix its scale and shift; view {missing.name} has none "
                "(supply a layout or metric depth)",
            )
        if not with_layout:
            fits[key] = ScaleFit(kind, 1.0, 0.0, float("nan"), float("nan"), 0)
            continue
        vals = np.concatenate([v.values.reshape(-1) for v in with_layout])
        lays = np.concatenate([v.layout.reshape(-1) for v in with_layout])
        fits[key] = fit_scale(
            vals,
            lays,
            kind,
            p.inlier_threshold,
            p.min_inlier_share,
            p.min_pixels,
            p.ransac_iterations,
            p.max_fit_pixels,
            p.seed,
            where=group[0].path if len(group) == 1 else depth_in.dir,
        )
    group_of = {v.name: key for key, group in groups.items() for v in group}
    assumed = [lv.view for lv in layout_views.values() if lv.camera_height_assumed]
    metric = fits.get("metric")
    if assumed and metric is not None and metric.num_pixels and abs(metric.scale - 1) > 0.05:
        # Metric depth is then likely right and the layout's scale wrong: say which to fix.
        ctx.warn(
            f"metric depth was rescaled by {metric.scale:.3f} to fit a layout whose camera height was "
            f"assumed for {', '.join(assumed)}; set camera_height in scene.json if the depth is metric"
        )

    # One ICP factor for the whole scene on top of the layout fits (scale-only, about each camera).
    layout_cloud = None
    if sampling_in is not None:
        layout_cloud = read_cloud(sampling_in.path(sampling_in.data.cloud.npz))
    icp_factor, icp_stats = 1.0, {}
    fitted = [v for v in views if fits[group_of[v.name]].num_pixels > 0]
    if p.icp and layout_cloud is not None and fitted and len(layout_cloud["points"]):
        rays, centres = [], []
        rng = np.random.default_rng(p.seed)
        quota = -(-p.icp_max_points // len(fitted))  # per view, so memory stays bounded
        for v in fitted:
            r, _, c = view_rays(fits[group_of[v.name]].apply(v.values), v.pose, max(p.stride, 1))
            if len(r) > quota:
                r = r[rng.choice(len(r), quota, replace=False)]
            rays.append(r)
            centres.append(np.broadcast_to(c, r.shape))
        r_all, c_all = np.concatenate(rays), np.concatenate(centres)
        lam, icp_stats = refine_scale_icp(
            c_all,
            r_all,
            layout_cloud["points"],
            layout_cloud["normals"],
            p.icp_max_distance,
            p.icp_iterations,
        )
        if abs(lam - 1.0) > p.icp_max_change:
            ctx.warn(f"ICP scale refinement {lam:.3f} exceeds icp_max_change; kept the layout fit")
        else:
            icp_factor = lam

    # Back-project with colours, merge.
    pts, cols = [], []
    for v in ctx.track(views, "back-projecting", total=len(views)):
        fit = fits[group_of[v.name]]
        depth = fit.apply(v.values) * (icp_factor if fit.num_pixels > 0 else 1.0)
        r, idx, c = view_rays(depth, v.pose, p.stride)
        h, w = v.values.shape
        rgb = read_rgb(v.image, size=(h, w))[:: p.stride, :: p.stride].reshape(-1, 3)
        vp, vc = c + r, rgb[idx]
        if p.voxel_size > 0:  # per view first: bounds memory before the scene-wide merge
            vp, vc = merge_points(vp, vc, p.voxel_size, 0)
        pts.append(vp)
        cols.append(vc)
    points = np.concatenate(pts) if pts else np.zeros((0, 3))
    colors = np.concatenate(cols) if cols else np.zeros((0, 3))
    if len(points) == 0:
        raise PanoError(depth_in.path(""), "no valid depth pixels in any view")
    points, colors = merge_points(points, colors, p.voxel_size, p.outlier_neighbors, p.outlier_std_ratio)

    normals = np.zeros_like(points)
    u0 = points.copy()
    is_layout = np.zeros(len(points), bool)
    if p.include_layout_points and layout_cloud is not None and len(layout_cloud["points"]):
        lc = layout_cloud
        points = np.concatenate([points, lc["points"]])
        colors = np.concatenate([colors, lc["colors"]])
        normals = np.concatenate([normals, lc["normals"]])
        u0 = np.concatenate([u0, lc["u0"]])
        is_layout = np.concatenate([is_layout, np.ones(len(lc["points"]), bool)])
    cloud = write_cloud(ctx.out_dir, points, colors, normals, u0, is_layout)

    reports = []
    for key, fit in fits.items():
        done = fit.num_pixels > 0
        lam = icp_factor if done else 1.0
        scale, shift = _with_factor(fit, lam)
        reports.append(
            KindFit(
                kind=fit.kind,
                depth_model=f"{DEPTH_MODELS[fit.kind]} ({EQUATIONS[fit.kind]})",
                views=[v.name for v in groups[key]],
                scale=scale,
                shift=shift,
                layout_fit_scale=fit.scale,
                icp_factor=lam,
                icp_fitness=icp_stats.get("fitness") if done else None,
                icp_rmse_m=icp_stats.get("rmse_m") if done else None,
                inlier_share=fit.inlier_share if done else None,
                residual_m=fit.residual_m if done else None,
                num_pixels=fit.num_pixels,
            )
        )
    main = max(reports, key=lambda r: len(r.views))
    return AlignOutput(
        cloud=cloud,
        scale=main.scale,
        shift=main.shift,
        inlier_share=main.inlier_share,
        residual_m=main.residual_m,
        aligned_to_layout=any(r.num_pixels > 0 for r in reports),
        fits=reports,
    )
