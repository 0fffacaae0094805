"""evaluate: render every held-out view of the trained model and measure it.

Per view: PSNR, SSIM, WS-PSNR, LPIPS (when weights are on the machine, else
reported unavailable with the reason), depth AbsRel / RMSE against ground
truth where the scene has it; render speed as the median FPS of repeated
full-panorama renders. Writes renders/, errors/, depth/, gt/ PNGs and
metrics.csv. With no test views it evaluates the training views and says so
(artifact `split: train`, a warning). See docs/evaluation.md.
"""

from __future__ import annotations

import csv
import math
import statistics
import time
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
import torch
from pydantic import Field, field_validator

from evaluation import metrics as M
from evaluation.model_io import (
    equirect_camera,
    load_model,
    recorded_background,
    render_on_device,
    render_pose,
)
from evaluation.visuals import depth_rgb, error_rgb
from panogeom.images import read_rgb, write_rgb
from runfs.errors import PanoError
from runfs.limits import read_image
from runtime.stage import Loaded, StageContext
from schemas.evaluate import EvaluateOutput, ViewMetrics
from schemas.scene import Scene, View
from schemas.scene_loader import read_depth_file, valid_mask
from schemas.stage_params import NAMES_FILE, StageParams
from splatting import DEFAULT_TILE, MAX_TILE

Output = EvaluateOutput

METRIC_KEYS = ("psnr", "ssim", "ws_psnr", "lpips", "depth_abs_rel", "depth_rmse", "psnr_colorfit", "ssim_colorfit",
               "flat_psnr", "flat_ssim")


class Params(StageParams):
    resolution: Literal["train", "image"] | tuple[int, int] = Field(
        default="train", json_schema_extra={"pixels": "hw"},
        description="Evaluation size: 'train' = the training (H, W) (ground truth area-downsampled to it), "
        "'image' = each test image's own size, or an explicit [H, W].",
    )
    backend: str | None = Field(default=None, description="Splatting backend (None: the renderer's default).")
    tile_size: int = Field(
        default=DEFAULT_TILE, ge=1, le=MAX_TILE, json_schema_extra={"pixels": "square"},
        description="The rasteriser's square tile in pixels: speed only, the images do not depend on it.")
    device: Literal["auto", "cpu", "cuda"] = Field(
        default="auto",
        description="Where the test views are rendered: auto = CUDA when available, else the CPU.")
    threads: int | None = Field(default=None, ge=1, description="torch threads while rendering (None: unchanged).")
    lpips: bool = Field(default=True, description="Compute LPIPS when weights are found.")
    lpips_net: Literal["alex", "vgg"] = Field(
        default="alex", description="LPIPS backbone: alex (the 3DGS papers' choice) or vgg.")
    lpips_weights: str | None = Field(
        default=None, json_schema_extra=NAMES_FILE,
        description="Folder or .pth with LPIPS weights; default $PANO_PIPE_LPIPS_WEIGHTS, then the standard places "
        "(torch hub cache for the backbone, the lpips wheel for the heads).",
    )
    lpips_download: bool = Field(
        default=True,
        description="Download a missing LPIPS backbone into the torch hub cache (off: $PANO_PIPE_OFFLINE).")
    fps_repeats: int = Field(default=5, ge=1, description="Renders timed for the median FPS.")
    background: tuple[float, float, float] | None = Field(
        default=None, description="Background colour behind the splats (None: the one training used)."
    )

    @field_validator("resolution")
    @classmethod
    def _positive(cls, v):
        if isinstance(v, tuple) and (v[0] < 2 or v[1] < 2):
            raise ValueError(f"an explicit resolution must be [H, W] with both >= 2, got {list(v)}")
        return v


def skip_reason(scene: Scene, params: Params) -> str | None:
    return None  # skipped only when its required input (train) is


# ----------------------------------------------------------------------------- pure helpers


def describe_mask(scene, view) -> str | None:
    """Which pixels a view's metrics leave out, in words (None: none)."""
    parts = []
    path = scene.mask_path(view)
    if path is not None:
        parts.append(path.relative_to(scene.root).as_posix() if path.is_relative_to(scene.root) else str(path))
    if scene.manifest.nadir_mask_deg > 0:
        parts.append(f"nadir cap {scene.manifest.nadir_mask_deg:g}°")
    return " + ".join(parts) or None


def training_mean_colour(scene: Scene, size: tuple[int, int]) -> np.ndarray | None:
    """The posed training panoramas' mean colour over their valid pixels at `size` (None without
    any): the flat image each view is also scored as (`flat_psnr`, `flat_ssim`). Where a model
    does not beat it, its held-out view lies beyond what the training views predict and the raw
    metrics measure exposure and smoothness (docs/evaluation.md)."""
    from gaussians.trainer import mean_colour

    views = [v for v in scene.manifest.train_views() if v.pose is not None]
    if not views:
        return None
    return np.asarray(mean_colour((read_rgb(scene.image_path(v), size=size), valid_mask(scene, v, *size))
                                  for v in views))


def mean_metrics(rows: list[dict]) -> dict[str, float]:
    """Mean of each metric over the rows that have it (None / NaN left out; a metric no row has is absent)."""
    out: dict[str, float] = {}
    for k in METRIC_KEYS:
        vals = [r[k] for r in rows if r.get(k) is not None and not math.isnan(r[k])]
        if vals:
            out[k] = float(np.mean(vals))
    return out


def write_csv(path: Path, rows: list[dict], mean: dict[str, float]) -> None:
    cols = ["view", "split", *METRIC_KEYS, "render_seconds"]
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(cols)
        for r in rows:
            w.writerow([_cell(r.get(c)) for c in cols])
        w.writerow(["mean", "", *[_cell(mean.get(k)) for k in METRIC_KEYS], ""])


def _cell(v) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return f"{v:.6g}"
    return str(v)


def eval_size(params: Params, train_resolution, image_shape: tuple[int, int]) -> tuple[int, int]:
    if params.resolution == "train":
        return int(train_resolution[0]), int(train_resolution[1])
    if params.resolution == "image":
        return int(image_shape[0]), int(image_shape[1])
    h, w = params.resolution
    return int(h), int(w)


def load_gt_depth(path: Path, size: tuple[int, int]) -> np.ndarray:
    """Ground-truth distance along the ray (.npy metres, or .png uint16 mm) at (H, W); nearest
    resampling so depth edges are not blended into values no surface has."""
    d = read_depth_file(path)  # the scene's depth format, as the depth stage reads supplied maps
    if d.shape != tuple(size):
        d = cv2.resize(d, (size[1], size[0]), interpolation=cv2.INTER_NEAREST)
    return d


def stitch_rig(tdata, size: tuple[int, int]):
    """The crops a perspective-trained model's test panoramas are stitched from (None for 360), their
    size scaled with the evaluation height: the baseline is evaluated as the paper states it."""
    if tdata.crops is None:
        return None
    return tdata.crops.rig(max(2, round(tdata.crops.size * size[0] / tdata.resolution[0])))


def render_seconds(render_once, device: str) -> float:
    """Seconds one call of `render_once` takes: on CUDA the time between two events recorded
    before and after it (the device's time, which includes any wait for the host's launches)."""
    if device != "cuda":
        t0 = time.perf_counter()
        render_once()
        return time.perf_counter() - t0
    start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
    start.record()
    render_once()
    end.record()
    end.synchronize()
    return start.elapsed_time(end) / 1000.0


def train_background(train: Loaded) -> tuple[float, float, float] | None:
    """The background the model was trained against, if recorded (`recorded_background`)."""
    return recorded_background(train.data.settings, None if train.meta is None else train.meta.params)


# ----------------------------------------------------------------------------- stage


#: LPIPS warnings already printed by this process: a batch or an ablation evaluates many times, and
#: the same missing weights are said once (each artifact still records the warning).
_LPIPS_SAID: set[str] = set()


def lpips_unavailable(ctx: StageContext, reason: str) -> None:
    """Warn that LPIPS is not computed, naming the setting that turns it off: printed once per process
    for one reason, recorded in every artifact."""
    message = f"LPIPS unavailable: {reason}; --set evaluate.lpips=false turns LPIPS off"
    if reason in _LPIPS_SAID:
        ctx.warnings.append(message)
    else:
        _LPIPS_SAID.add(reason)
        ctx.warn(message)


def run(ctx: StageContext) -> EvaluateOutput:
    p: Params = ctx.params
    train = ctx.inputs["train"]
    tdata = train.data
    views: list[View] = ctx.scene.manifest.test_views()
    split = "test"
    if not views:
        views = ctx.scene.manifest.train_views()
        split = "train"
        ctx.warn("the scene has no test views: evaluating on the TRAINING views (a fit, not generalisation)")

    background = p.background if p.background is not None else train_background(train)
    from stages.train import resolve_device

    device = resolve_device(p.device, "evaluate.device")  # cuda without CUDA: a one-line input error
    old_threads = torch.get_num_threads()
    if p.threads:
        torch.set_num_threads(p.threads)
    try:
        g = load_model(train.path(tdata.ply), device=device)
        lpips_model, lpips_reason = None, None
        if p.lpips:
            try:
                lpips_model = M.load_lpips(p.lpips_net, p.lpips_weights, p.lpips_download)
            except M.LpipsUnavailable as e:
                lpips_reason = str(e)
                lpips_unavailable(ctx, lpips_reason)
        else:
            lpips_reason = "disabled by parameter evaluate.lpips=false"

        out = ctx.out_dir
        for sub in ("renders", "errors", "depth", "gt"):
            (out / sub).mkdir(parents=True, exist_ok=True)
        rows: list[dict] = []
        results: list[ViewMetrics] = []
        size = None
        flat, flat_known = None, False
        backend = p.backend or "?"
        for v in ctx.track(views, "evaluate: views", total=len(views)):
            img_path = ctx.scene.image_path(v)
            native = read_image(img_path)
            if native is None:
                raise PanoError(img_path, "unreadable image")
            size = eval_size(p, tdata.resolution, native.shape[:2])
            gt = read_rgb(img_path, size=size)
            r = render_pose(g, v.pose_matrix, equirect_camera(*size), backend=p.backend, background=background,
                            rig=stitch_rig(tdata, size), tile_size=p.tile_size)
            backend = r.backend
            mask = valid_mask(ctx.scene, v, *size)
            if not flat_known:  # once: the mean colour hardly depends on the size
                flat, flat_known = training_mean_colour(ctx.scene, size), True
            m = M.view_metrics(r.image, gt, lpips_model, mask, flat)
            row = {"view": v.name, "split": split, **m, "render_seconds": r.seconds}
            gt_depth_path = ctx.scene.gt_depth_path(v)
            dm = None
            if gt_depth_path is not None and gt_depth_path.is_file():
                dm = M.depth_metrics(r.depth, load_gt_depth(gt_depth_path, size), mask)
                row["depth_abs_rel"] = dm["abs_rel"] if dm["count"] else None
                row["depth_rmse"] = dm["rmse"] if dm["count"] else None
            names = {k: f"{k}/{v.name}.png" for k in ("gt", "renders", "errors", "depth")}
            write_rgb(out / names["gt"], gt)
            write_rgb(out / names["renders"], r.image)
            write_rgb(out / names["errors"], error_rgb(M.error_map(r.image, gt), valid=mask))  # masked: grey
            write_rgb(out / names["depth"], depth_rgb(r.depth))
            np.save(out / "depth" / f"{v.name}.npy", r.depth.astype(np.float32))
            rows.append(row)
            results.append(
                ViewMetrics(
                    view=v.name, split=split, psnr=m["psnr"], ssim=m["ssim"], ws_psnr=m["ws_psnr"], lpips=m["lpips"],
                    psnr_colorfit=m["psnr_colorfit"], ssim_colorfit=m["ssim_colorfit"],
                    flat_psnr=m["flat_psnr"], flat_ssim=m["flat_ssim"],
                    depth_abs_rel=row.get("depth_abs_rel"), depth_rmse=row.get("depth_rmse"),
                    depth_valid_pixels=dm["count"] if dm else None, render_seconds=r.seconds,
                    gt=names["gt"], render=names["renders"], error=names["errors"], depth=names["depth"],
                    depth_npy=f"depth/{v.name}.npy", mask=describe_mask(ctx.scene, v),
                )
            )

        # Speed: the first view again, timed; its first render above was the warm-up. A frame is
        # pose in, panorama on the device out (as 3DGS and gsplat count FPS): the download to
        # host memory and the metrics are not part of rendering it.
        pose, cam, rig = views[0].pose_matrix, equirect_camera(*size), stitch_rig(tdata, size)
        times = [render_seconds(lambda: render_on_device(g, pose, cam, backend=p.backend, background=background,
                                                         rig=rig, tile_size=p.tile_size),
                                device) for _ in range(p.fps_repeats)]
        fps = 1.0 / max(statistics.median(times), 1e-9)
        threads = torch.get_num_threads()
    finally:
        torch.set_num_threads(old_threads)

    below = [r["view"] for r in rows if split == "test" and r["flat_psnr"] is not None and r["psnr"] is not None
             and r["psnr"] <= r["flat_psnr"]]
    if below:
        ctx.warn(f"{len(below)} of {len(rows)} held-out views score no higher PSNR than a flat image of the training "
                 f"panoramas' mean colour ({', '.join(below[:5])}{', ...' if len(below) > 5 else ''}): there the "
                 "raw metrics measure exposure and smoothness, not the reconstruction (compare psnr_colorfit)")
    mean = mean_metrics(rows)
    write_csv(out / "metrics.csv", rows, mean)
    return EvaluateOutput(
        views=results,
        mean=mean,
        csv="metrics.csv",
        split=split,
        on_train_views=split == "train",
        resolution=size,
        lpips_available=lpips_model is not None,
        lpips_reason=lpips_reason,
        lpips_net=p.lpips_net if lpips_model is not None else None,
        fps=fps,
        fps_repeats=p.fps_repeats,
        backend=backend,
        device=device,
        threads=threads,
        num_gaussians=len(g),
        stitched=None if tdata.crops is None else
        f"{len(tdata.crops.names)} crops of {tdata.crops.fov_deg:g}°, {stitch_rig(tdata, size).size} px",
    )
