"""align: per-view depth scaled to the layout, back-projected, merged and joined with the layout cloud.

1. The depth the layout implies: every pixel's ray is cast against the view's
   metric room (floor y = +h, ceiling y = -d, vertical walls on the floor
   polygon, all in the camera frame) -> layout depth and a wall/floor/ceiling
   label (`floorplan.layout_depth`).
2. A robust fit of the depth to the layout depth, robust to furniture and
   noise: RANSAC on minimal samples, least squares on the inliers (relative
   error below `inlier_threshold`), then IRLS with Tukey's biweight. The
   model of depth decides the unknowns and the groups: metric distance, one
   scale for all views (the paper's global factor); affine depth, scale and
   shift; affine inverse depth (Depth Anything), scale and shift in inverse
   depth, 1/d = s*v + t, per view (`depthalign.scale_fit`).
3. Refinement against the layout cloud by a scale-only point-to-plane ICP
   (`depthalign.clouds.refine_scale_icp`): the scale acts about each camera centre because the
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

from depthalign.clouds import merge_points, refine_scale_icp, view_rays
from depthalign.scale_fit import ScaleFit, fit_scale
from floorplan.layout_depth import layout_depth_map
from panogeom.surfaces import SURFACE_NAMES
from runfs.errors import PanoError
from runfs.limits import load_npy
from runtime.stage import StageContext
from schemas.align import AlignOutput, KindFit
from schemas.depth import DEPTH_MODELS
from schemas.scene import Scene
from schemas.scene_loader import valid_mask
from schemas.stage_params import StageParams

Output = AlignOutput

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


def fit_settings(p: Params) -> dict:
    """The robust fit's settings (`depthalign.scale_fit.fit_scale`'s keywords) from the stage's."""
    return {"inlier_threshold": p.inlier_threshold, "min_inlier_share": p.min_inlier_share,
            "min_pixels": p.min_pixels, "ransac_iterations": p.ransac_iterations,
            "max_pixels": p.max_fit_pixels, "seed": p.seed}


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
        fits[key] = fit_scale(vals, lays, kind, **fit_settings(p),
                              where=group[0].path if len(group) == 1 else depth_in.dir)
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
        lam, icp_stats = refine_scale_icp(c_all, r_all, layout_cloud["points"], layout_cloud["normals"],
                                          max_distance=p.icp_max_distance, iterations=p.icp_iterations)
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
            vp, vc = merge_points(vp, vc, voxel_size=p.voxel_size, nb_neighbors=0, std_ratio=p.outlier_std_ratio)
        pts.append(vp)
        cols.append(vc)
    points = np.concatenate(pts) if pts else np.zeros((0, 3))
    colors = np.concatenate(cols) if cols else np.zeros((0, 3))
    if len(points) == 0:
        raise PanoError(depth_in.path(""), "no valid depth pixels in any view")
    points, colors = merge_points(points, colors, voxel_size=p.voxel_size, nb_neighbors=p.outlier_neighbors,
                                  std_ratio=p.outlier_std_ratio)

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
        scale, shift = fit.times(lam)
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
