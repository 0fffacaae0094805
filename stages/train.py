"""train: layout-guided 360° Gaussian splatting (the optimisation of 360-GS).

Glue only: resolve the preset and the initialisation, load the training
images, run gaussians.trainer.Trainer with a rich progress bar, checkpoints
(every `checkpoint_every` iterations and on Ctrl-C or SIGTERM) and --resume, and
export the standard 3DGS PLY. The math lives in gaussians/. See docs/training.md.
"""

from __future__ import annotations

import hashlib
import json
import signal
import threading
import time
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from pydantic import Field, field_validator, model_validator
from rich.markup import escape

import splatting
from gaussians.config import TrainConfig
from gaussians.init import from_cloud, random_points
from gaussians.model import DEFAULT_EPS2D, Gaussians
from gaussians.ply import nonfinite_problem, save_ply
from gaussians.trainer import CHECKPOINT_NAME, Trainer, TrainView, scene_extent
from panogeom.images import read_rgb
from panogeom.resample import perspective_crop
from runfs.errors import PanoError, one_line
from runtime.stage import StageContext
from schemas.scene import Scene, View
from schemas.scene_loader import valid_mask
from schemas.stage_params import StageParams
from schemas.train import CropRig, TrainOutput

Output = TrainOutput


#: What each preset fills in for the parameters left unset (None).
PRESETS: dict[str, dict] = {
    # CPU default: small panoramas, short schedule, modest cap. On the demo scene the held-out PSNR
    # plateaus after ~1200 iterations (docs/training.md), so 2000 keep make demo well under 10 minutes.
    "fast": dict(height=128, iterations=2000, densify_from=500, densify_until=1500, opacity_reset_every=3000,
                 max_gaussians=50_000, random_points=20_000, max_init_points=30_000),
    # the paper's setting (512×1024, 7k iterations; 3DGS densifies up to 15k, i.e. all of it)
    "paper": dict(height=512, iterations=7000, densify_from=500, densify_until=15_000, opacity_reset_every=3000,
                  max_gaussians=1_000_000, random_points=100_000, max_init_points=0),
    # the full 3DGS schedule
    "quality": dict(height=512, iterations=30_000, densify_from=500, densify_until=15_000,
                    opacity_reset_every=3000, max_gaussians=3_000_000, random_points=100_000, max_init_points=0),
}


#: Defaults that depend on the projection, for the parameters left unset (None). The 360 path's
#: controls for sparse captures, measured in docs/training.md ("Sparse captures: 360° against crops");
#: the perspective baselines keep 3DGS's behaviour.
PROJECTION_DEFAULTS: dict[str, dict] = {
    "360": dict(random_background=False, random_turns=True, eps2d=0.05, lr_scale=0.5, mip_filter=False),
    "crops": dict(random_background=False, random_turns=False, eps2d=DEFAULT_EPS2D, lr_scale=1.0, mip_filter=False),
    "cubemap": dict(random_background=False, random_turns=False, eps2d=DEFAULT_EPS2D, lr_scale=1.0, mip_filter=False),
}


#: The trainer's defaults, which the settings below take as theirs (one place for each number)
_TRAINER = TrainConfig().flat()
#: The learning rates `lr_scale` multiplies
_SCALED_LRS = ("lr_position_init", "lr_position_final", "lr_sh_dc", "lr_sh_rest", "lr_opacity", "lr_scaling",
               "lr_rotation")


class Params(StageParams):
    preset: Literal["fast", "paper", "quality"] = Field(
        default="fast", description="Fills every setting left unset: fast (CPU), paper (512x1024, 7k), quality (30k).")
    iterations: int | None = Field(
        default=None, ge=1,
        description="Optimisation steps, one training panorama each (None: the preset's).")
    height: int | None = Field(default=None, ge=8, json_schema_extra={"pixels": "panorama_height"},
                               description="Training panorama height; width = 2 x height.")
    init: Literal["auto", "random", "layout", "depth", "layout+depth"] = Field(
        default="auto",
        description="auto = layout+depth with the align stage, layout with sampling only, random otherwise.")
    projection: Literal["360", "crops", "cubemap"] = Field(
        default="360", description="360 = equirectangular splatting; crops = the paper's 3D-GS baseline "
                                   "(pinhole crops, crop_*); cubemap = six 90° faces of W/4.")
    crop_fov: float = Field(default=splatting.PAPER_CROPS["fov_deg"], gt=0, lt=180,
                            description="Field of view of a crop (degrees).")
    crop_elevations: tuple[float, ...] = Field(
        default=splatting.PAPER_CROPS["elevations"], description="Elevations of the crop rings (degrees, up positive).")
    crop_counts: tuple[int, ...] = Field(
        default=splatting.PAPER_CROPS["counts"], description="Crops per elevation ring, yaws evenly spread from 0 (paper: 8 in all).")
    crop_size: int | None = Field(
        default=None, ge=8, json_schema_extra={"pixels": "square"},
        description="Crop side in pixels (None = the training height: 512 at 512x1024).")
    layout_reg: bool = Field(
        default=_TRAINER["layout_reg"], description="L_layout on/off (ablation); needs the layout cloud of the sampling stage.")
    lambda_l1: float = Field(default=_TRAINER["lambda_l1"], ge=0, description="λ1: weight of the L1 photometric loss.")
    lambda_dssim: float = Field(
        default=_TRAINER["lambda_dssim"], ge=0, description="λ2: weight of the D-SSIM loss (1 - SSIM) / 2.")
    solid_angle_weighting: bool = Field(
        default=_TRAINER["solid_angle_weighting"], description="360: weigh each panorama pixel's L1 and SSIM by its solid angle (cos latitude).")
    lambda_scale: float = Field(
        default=_TRAINER["lambda_scale"], ge=0, description="Weight of the mean-scale penalty (mean Gaussian scale / extent; official 360-GS).")
    max_anisotropy: float | None = Field(
        default=None, ge=1, description="Longest / second-longest axis of a Gaussian at most this (None = free): "
                                       "no needles.")
    crop_loss: bool = Field(
        default=_TRAINER["crop_loss"], description="360: measure L1 and D-SSIM on the eight 120° perspective crops resampled "
                                   "from the rendered panorama instead of on the panorama itself (the paper's crops at the panorama's "
                                   "height, whatever crop_* say: those are the crops projection's).")
    lambda_coverage: float = Field(
        default=_TRAINER["lambda_coverage"], ge=0, description="Weight of the novel-view coverage loss: mean(1 - alpha) of a small panorama "
        "rendered from a random point between the training cameras (indoors every ray ends on a surface); "
        "sparse captures: 1 with lr_scale=0.125 (docs/training.md).")
    coverage_height: int | None = Field(
        default=None, ge=4, json_schema_extra={"pixels": "panorama_height"},
        description="Rows of the coverage loss's panorama (None = half the training height: "
        "a coarser render blurs the holes between thin splats shut, a full-size one costs a second render).")
    random_turns: bool | None = Field(
        default=None, description="360: turn each training panorama's camera by a random rotation every time it "
        "is drawn (free yaw, tilt up to random_turn_tilt_deg), its ground truth resampled to match: the model is "
        "supervised between the pixel centres, as the crops are. None = the projection's default (on for 360).")
    random_turn_tilt_deg: float = Field(
        default=_TRAINER["random_turn_tilt_deg"], ge=0, le=180, description="Largest tilt of those turns (degrees).")
    random_turn_interp: Literal["bilinear", "bicubic"] = Field(
        default=_TRAINER["random_turn_interp"], description="Interpolation of the turned ground truth (bicubic blurs it less).")
    eps2d: float | None = Field(
        default=None, ge=0, description="The renderer's screen-space dilation (squared pixels) the model is "
        "fitted with and, saved with it, drawn with. None = the projection's default: 0.05 for 360 (with "
        "random_turns: a model fitted with 3DGS's 0.3 leaves holes when seen finer), 0.3 for the crops.")
    mip_filter: bool | None = Field(
        default=None, description="Mip-Splatting's 3D smoothing filter: each Gaussian drawn convolved with a 3D "
        "low-pass as wide as the finest training camera's sampling interval at it (no needles thinner than a "
        "training pixel); the exported model holds the filtered scales and opacities. None = the projection's "
        "default (off for every projection).")
    mip_filter_variance: float = Field(
        default=_TRAINER["mip_filter_variance"], gt=0, description="The low-pass's variance in squared sampling intervals (Mip-Splatting: 0.2).")
    mip_filter_keep_integral: bool = Field(
        default=_TRAINER["mip_filter_keep_integral"], description="Lower a widened Gaussian's opacity so its integral stays (Mip-Splatting); "
                                  "false widens only (an ablation).")
    lambda_layout: float | None = Field(
        default=None, ge=0,
        description="λ3, weight of L_layout; default 0.1 for <= 8 training views, 0.01 above (paper).")
    layout_deadzone: float = Field(
        default=_TRAINER["layout_deadzone"], ge=0,
        description="Displacements from a layout Gaussian's anchor up to this length (scene units) are free "
        "of L_layout (the official 360-GS code's normal_threshold); 0 = the paper's term everywhere, which "
        "locks a layout Gaussian at its anchor.")
    lr_scale: float | None = Field(
        default=None, gt=0, description="Multiplies every learning rate below. None = the projection's default: "
        "0.5 for 360 (a panorama iteration updates every Gaussian, a crop iteration about a quarter of them), "
        "1 for the crops.")
    lr_position_init: float = Field(
        default=_TRAINER["lr_position_init"], gt=0,
        description="Adam learning rate of the Gaussian centres at iteration 1, × extent (m).")
    lr_position_final: float = Field(
        default=_TRAINER["lr_position_final"], gt=0,
        description="The centres' learning rate at the last iteration, × extent (exponential decay in "
                    "between).")
    lr_sh_dc: float = Field(
        default=_TRAINER["lr_sh_dc"], ge=0, description="Adam learning rate of the base colour (SH band 0).")
    lr_sh_rest: float = Field(
        default=_TRAINER["lr_sh_rest"], ge=0,
        description="Adam learning rate of the view-dependent colour (SH bands 1-3).")
    lr_opacity: float = Field(default=_TRAINER["lr_opacity"], ge=0, description="Adam learning rate of the opacity logits.")
    lr_scaling: float = Field(
        default=_TRAINER["lr_scaling"], ge=0, description="Adam learning rate of the log scales (log metres).")
    lr_rotation: float = Field(
        default=_TRAINER["lr_rotation"], ge=0, description="Adam learning rate of the rotation quaternions.")
    extent: float | None = Field(
        default=None, gt=0, description="Scene size (m); default half the diagonal of the initial points' box.")
    sh_degree: int = Field(
        default=_TRAINER["sh_degree"], ge=0, le=3, description="Highest spherical-harmonics degree of the colours.")
    sh_degree_every: int = Field(
        default=_TRAINER["sh_degree_every"], ge=1, description="Iterations between turning on one more SH degree (up to sh_degree).")
    densify_from: int | None = Field(
        default=None, ge=0,
        description="First iteration that clones, splits and prunes (None: the preset's).")
    densify_until: int | None = Field(
        default=None, ge=0, description="Last iteration that densifies (None: the preset's).")
    densify_every: int = Field(default=_TRAINER["densify_every"], ge=1, description="Iterations between densification steps.")
    densify_grad_threshold: float = Field(
        default=_TRAINER["densify_grad_threshold"], gt=0, description="On the angular view-space gradient (resolution independent).")
    percent_dense: float = Field(
        default=_TRAINER["percent_dense"], gt=0, description="Gaussians larger than this × extent are split, smaller ones cloned.")
    min_opacity: float = Field(
        default=_TRAINER["min_opacity"], ge=0, lt=1, description="Densification prunes Gaussians less opaque than this.")
    opacity_reset_every: int | None = Field(
        default=None, ge=0, description="Iterations between opacity resets (0 = never; None: the preset's).")
    max_world_scale: float | None = Field(
        default=_TRAINER["max_world_scale"], gt=0, description="Prune scale > this × extent after the first opacity reset (None = off).")
    max_screen_radius: float | None = Field(
        default=None, gt=0, description="Prune a screen radius > this (radians) after the first reset.")
    size_prune_from: int | None = Field(
        default=None, ge=0, description="Iteration from which max_world_scale / max_screen_radius prune "
                                        "(None = after the first opacity reset).")
    max_gaussians: int | None = Field(default=None, ge=1, description="Densification cap.")
    random_points: int | None = Field(default=None, ge=1, description="Gaussians of the random init.")
    max_init_points: int | None = Field(
        default=None, ge=0, description="Random subset of a larger init cloud (0 = keep all).")
    init_opacity: float = Field(default=0.1, gt=0, lt=1, description="Opacity of every initial Gaussian.")
    layout_flatten: float = Field(default=0.1, gt=0, le=1, description="Thickness / width of layout Gaussians.")
    background: tuple[float, float, float] | Literal["mean"] = Field(
        default="mean", description="RGB in [0, 1] behind the Gaussians while training and in the evaluation's "
        "renders, or 'mean': the training images' mean colour, so what no training view covers shows the colour "
        "that costs least (docs/training.md, issue 39: +3.5 dB on a real panorama 3.6 m from its training view).")
    random_background: bool | None = Field(
        default=None, description="Train against a random background colour each iteration (opaque surfaces); "
                                  "evaluation renders use `background`. None = the projection's default "
                                  "(off for every projection).")
    seed: int = Field(
        default=_TRAINER["seed"], ge=0, le=2**32 - 1,
        description="Random seed of the view order, random init and densification.")
    backend: Literal["cpp", "cuda", "torch"] | None = Field(
        default=None, description="splatting backend; None = its default for the device (cpp on CPU, cuda on CUDA).")
    tile_size: int = Field(
        default=splatting.DEFAULT_TILE, ge=1, le=splatting.MAX_TILE, json_schema_extra={"pixels": "square"},
        description="The rasteriser's square tile in pixels: speed only, the images do not depend on it "
                    "(docs/gpu.md, tile size).")
    device: Literal["auto", "cpu", "cuda"] = Field(
        default="auto", description="Where training runs: auto = CUDA when available, else the CPU.")
    threads: int | None = Field(default=None, ge=1, description="torch threads (None = leave as is).")
    log_every: int = Field(default=_TRAINER["log_every"], ge=1, description="Iterations between records in train_log.jsonl.")
    checkpoint_every: int = Field(default=_TRAINER["checkpoint_every"], ge=0, description="0 = only on Ctrl-C.")
    appearance: bool = Field(default=_TRAINER["appearance"], description="A learned colour gain and bias per training panorama "
                                                       "(exposure, white balance), applied while training only.")
    lambda_appearance: float = Field(default=_TRAINER["lambda_appearance"], ge=0, description="Weight pulling the transforms to identity.")
    lr_appearance: float = Field(default=_TRAINER["lr_appearance"], gt=0, description="Adam learning rate of the transforms.")
    pin_appearance_mean: bool = Field(
        default=_TRAINER["pin_appearance_mean"], description="Hold the mean transform over the panoramas at the identity exactly "
        "(a projection after each step): the model's colours then match the panoramas' mean exposure, which "
        "held-out views are rendered at.")

    @field_validator("background", mode="before")
    @classmethod
    def _mean_or_rgb(cls, v):
        if isinstance(v, str) and v != "mean":
            raise ValueError(f"{v!r} is neither 'mean' nor an RGB triple [r, g, b] in [0, 1]")
        return v

    def resolved(self, key: str):
        """The value of `key`: as set, else the preset's, else the projection's default (PROJECTION_DEFAULTS)."""
        v = getattr(self, key)
        if v is not None:
            return v
        return self.default(key)

    def default(self, key: str):
        """What `key` is when left unset, with this preset and projection: the preset's value, else
        the projection's default, else the field's own."""
        if key in PRESETS[self.preset]:
            return PRESETS[self.preset][key]
        if key in PROJECTION_DEFAULTS[self.projection]:
            return PROJECTION_DEFAULTS[self.projection][key]
        return type(self).model_fields[key].get_default(call_default_factory=True)

    def values_used(self) -> dict:
        """Every setting's value used (``resolved``), as JSON data."""
        return {k: list(v) if isinstance(v, tuple) else v for k in type(self).model_fields
                for v in (self.resolved(k),)}

    @model_validator(mode="after")
    def _crops_form_rings(self):
        splatting.crop_rig(8, self.crop_fov, self.crop_elevations, self.crop_counts)  # ValueError says what is wrong
        return self

    def rig(self, height: int) -> splatting.PerspectiveRig | None:
        """The perspective crops this projection trains on at panorama height `height` (None for 360)."""
        if self.projection == "cubemap":
            return splatting.cubemap_rig(max(height // 2, 2))  # face W/4
        if self.projection == "crops":
            return splatting.crop_rig(self.crop_size or height, self.crop_fov, self.crop_elevations,
                                      self.crop_counts)
        return None


def skip_reason(scene: Scene, params: Params) -> str | None:
    return None  # every scene with training views trains


# ----------------------------------------------------------------------------- pure helpers


def default_lambda_layout(num_train_views: int) -> float:
    """The paper's λ3: 0.1 for sparse captures (≤ 8 panoramas), 0.01 for dense ones."""
    return 0.1 if num_train_views <= 8 else 0.01


def resolve_init(requested: str, has_align: bool, align_has_layout: bool, align_has_depth: bool,
                 has_sampling: bool) -> str:
    """The initialisation to use; raises ValueError (with why) when the requested one is unavailable."""
    if requested == "auto":
        if has_align and align_has_layout and align_has_depth:
            return "layout+depth"
        if has_align and align_has_depth:
            return "depth"
        if has_sampling or (has_align and align_has_layout):
            return "layout"
        return "random"
    if requested == "layout+depth" and not (has_align and align_has_layout and align_has_depth):
        raise ValueError("init 'layout+depth' needs the align stage with both layout and depth points")
    if requested == "depth" and not (has_align and align_has_depth):
        raise ValueError("init 'depth' needs the align stage (depth points)")
    if requested == "layout" and not (has_sampling or (has_align and align_has_layout)):
        raise ValueError("init 'layout' needs the sampling stage (or an align cloud with layout points)")
    return requested


def select_cloud(init: str, align: dict | None, sampling: dict | None) -> dict:
    """The points an init uses: align's cloud whole, only its depth points, or the layout points."""
    def subset(c: dict, mask: np.ndarray) -> dict:
        return {k: v[mask] for k, v in c.items()}

    if init == "layout+depth":
        return align
    if init == "depth":
        return subset(align, ~align["is_layout"])
    if init == "layout":
        if sampling is not None:
            return sampling
        return subset(align, align["is_layout"])
    raise ValueError(init)


def subsample_cloud(cloud: dict, max_points: int, seed: int) -> dict:
    """A uniform random subset of at most `max_points` points (same seed, same subset)."""
    n = len(cloud["points"])
    if max_points <= 0 or n <= max_points:
        return cloud
    idx = np.sort(np.random.default_rng(seed).choice(n, size=max_points, replace=False))
    return {k: v[idx] for k, v in cloud.items()}


def build_views(images: dict[str, np.ndarray], viewmats: dict[str, np.ndarray], projection: str,
                masks: dict[str, np.ndarray | None] | None = None,
                rig: splatting.PerspectiveRig | None = None) -> list[TrainView]:
    """Training views: one equirectangular view per panorama, or the crops of `rig` (default: the
    projection's default rig, Params().rig) named `<panorama>/<crop>`; `masks` ([H,W] bool per view,
    None = all valid) are resampled to the crops like the images."""
    out = []
    for name, img in images.items():
        vm = torch.as_tensor(viewmats[name], dtype=torch.float32)
        h, w = img.shape[:2]
        mask = (masks or {}).get(name)
        if projection == "360":
            out.append(TrainView(name, torch.from_numpy(np.ascontiguousarray(img)), vm,
                                 splatting.EquirectCamera(h, w),
                                 None if mask is None else torch.from_numpy(np.ascontiguousarray(mask))))
            continue
        crops = rig or Params(projection=projection).rig(h)
        for crop, (cv, cam) in zip(crops.names, crops.crops()):
            gt = perspective_crop(img, cv.numpy(), cam)
            crop_mask = None
            if mask is not None:
                # a crop pixel is valid when the bilinear sample draws only on valid panorama pixels
                m = perspective_crop(mask.astype(np.float32), cv.numpy(), cam)
                crop_mask = torch.from_numpy(np.ascontiguousarray(m > 0.999))
                if not bool(crop_mask.any()):
                    continue  # a crop wholly masked out (the nadir face under a big cap) is not trained on
            out.append(TrainView(f"{name}/{crop}", torch.from_numpy(np.ascontiguousarray(gt)), cv @ vm, cam,
                                 crop_mask))
    return out


def make_config(p: Params, num_train_views: int, extent: float, device: str = "cpu") -> TrainConfig:
    """The trainer's configuration: every setting it shares with Params as resolved (preset, then
    projection defaults), the learning rates times `lr_scale`, and what the stage derives."""
    shared = set(TrainConfig.setting_names()) & set(Params.model_fields)
    values = {k: p.resolved(k) for k in shared}
    lr = float(p.resolved("lr_scale"))
    values.update({k: lr * values[k] for k in _SCALED_LRS})
    values.update(
        iterations=int(values["iterations"]), densify_from=int(values["densify_from"]),
        densify_until=int(values["densify_until"]), opacity_reset_every=int(values["opacity_reset_every"]),
        eps2d=float(values["eps2d"]),
        background=(values["background"] if values["background"] == "mean"
                    else tuple(float(x) for x in values["background"])),
        lambda_layout=p.lambda_layout if p.lambda_layout is not None else default_lambda_layout(num_train_views),
        coverage_height=p.coverage_height or max(4, int(p.resolved("height")) // 2),
        extent=float(extent), device=device,
    )
    return TrainConfig.of(**values)


def init_fingerprint(g: Gaussians, views: list[TrainView]) -> str:
    """Hash of the initial model and training images: a checkpoint only resumes the same run."""
    h = hashlib.sha256()
    for k, v in g.tensors().items():
        h.update(k.encode())
        h.update(v.detach().cpu().contiguous().numpy().tobytes())
    for v in views:
        h.update(v.name.encode())
        h.update(v.image.contiguous().numpy().tobytes())
        h.update(v.viewmat.contiguous().numpy().tobytes())
        if v.mask is not None:
            h.update(v.mask.contiguous().numpy().tobytes())
    return h.hexdigest()[:16]


# ----------------------------------------------------------------------------- glue


def _load_cloud(ctx: StageContext, name: str) -> dict | None:
    from stages.cloud_io import read_cloud

    loaded = ctx.inputs.get(name)
    if loaded is None:
        return None
    return read_cloud(loaded.path(loaded.data.cloud.npz))


def initial_gaussians(ctx: StageContext, p: Params, views: list[View]) -> tuple[Gaussians, str]:
    align = _load_cloud(ctx, "align")
    sampling = _load_cloud(ctx, "sampling")
    try:
        init = resolve_init(
            p.init, has_align=align is not None,
            align_has_layout=align is not None and bool(align["is_layout"].any()),
            align_has_depth=align is not None and bool((~align["is_layout"]).any()),
            has_sampling=sampling is not None and len(sampling["points"]) > 0,
        )
    except ValueError as e:
        raise PanoError("train.init", str(e)) from None
    if init == "random":
        union = ctx.inputs.get("union")
        rooms = union.data.rooms if union is not None else None
        positions = np.stack([v.position for v in views])
        g = random_points(int(p.resolved("random_points")), p.seed, rooms=rooms or None,
                          camera_positions=positions, sh_degree=p.sh_degree, init_opacity=p.init_opacity)
    else:
        cloud = subsample_cloud(select_cloud(init, align, sampling), int(p.resolved("max_init_points")), p.seed)
        if len(cloud["points"]) == 0:
            raise PanoError("train.init", f"init {init!r}: the point cloud is empty")
        g = from_cloud(cloud, sh_degree=p.sh_degree, init_opacity=p.init_opacity, layout_flatten=p.layout_flatten)
    return g, init


def load_images(scene: Scene, views: list[View], height: int, warn=None) -> dict[str, np.ndarray]:
    """The training images at height x 2*height; `warn` is told which were smaller (upsampled:
    the model then learns interpolated detail)."""
    from runfs.limits import image_size

    out, small = {}, []
    for v in views:
        path = scene.image_path(v)
        native = image_size(path)
        if native is not None and native[0] < height:  # (H, W)
            small.append(f"{v.name} ({native[1]}x{native[0]})")
        try:
            out[v.name] = read_rgb(path, size=(height, 2 * height))
        except ValueError:
            raise PanoError(path, "unreadable image") from None
    if small and warn is not None:
        warn(f"{len(small)} training image(s) smaller than the training size {2 * height}x{height}, upsampled: "
             + ", ".join(small[:4]) + (" ..." if len(small) > 4 else "")
             + "; set train.height to the images' height or less")
    return out


class _DeferredInterrupt:
    """Ctrl-C or SIGTERM (a scheduler or `kill` stopping the job) between iterations: the first
    one sets a flag the loop checks (so the checkpoint is written at a consistent state), a
    second one interrupts at once. The previous handlers come back on exit."""

    SIGNALS = tuple(getattr(signal, name) for name in ("SIGINT", "SIGTERM") if hasattr(signal, name))

    def __init__(self):
        self.requested = False
        self._old: dict[int, object] = {}

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():  # signal.signal works only there
            for sig in self.SIGNALS:
                self._old[sig] = signal.getsignal(sig)
                signal.signal(sig, self._handler)
        return self

    def _handler(self, signum, frame):
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True

    def __exit__(self, *exc):
        for sig, old in self._old.items():
            # None: a handler not installed from Python, which cannot be put back; SIG_DFL is what it was
            signal.signal(sig, old if old is not None else signal.SIG_DFL)
        self._old.clear()
        return False


def run(ctx: StageContext) -> TrainOutput:
    from rich.progress import TextColumn

    from runtime.console import KEEP_FIELD, RecentRate, console, make_progress

    p: Params = ctx.params
    if p.threads:
        torch.set_num_threads(p.threads)
    views = ctx.scene.manifest.train_views()
    height = int(p.resolved("height"))
    images = load_images(ctx.scene, views, height, warn=ctx.warn)
    masks = {v.name: valid_mask(ctx.scene, v, height, 2 * height) for v in views}
    rig = p.rig(height)
    if rig is not None:
        try:  # the crops must see every direction, or the stitched test panoramas would have holes
            splatting.stitch_table(height, 2 * height, rig)
        except ValueError as e:
            raise PanoError("train.crop_fov", str(e)) from None
    train_views = build_views(images, {v.name: v.viewmat for v in views}, p.projection, masks, rig)
    g, init = initial_gaussians(ctx, p, views)
    extent = p.extent if p.extent is not None else scene_extent(g.means)
    device = resolve_device(p.device, "train.device")
    cfg = make_config(p, len(views), extent, device)

    kernel_build_s = build_kernel_first(p.backend, device)
    log_path = ctx.out_dir / "train_log.jsonl"
    trainer = Trainer(g, train_views, cfg, log_path=log_path)
    trainer.extra_fingerprint = init_fingerprint(g, train_views)
    scratch = Path(ctx.scratch_dir) if ctx.scratch_dir is not None else None
    ckpt = scratch / CHECKPOINT_NAME if scratch is not None else None
    resumed_from = None
    if ctx.resume:
        if ckpt is None or not ckpt.is_file():
            ctx.warn("--resume: no training checkpoint found; training from the start")
        else:
            try:
                trainer.load_checkpoint(ckpt)
                resumed_from = trainer.iteration
                console.print(f"resuming training from iteration {resumed_from} ({escape(str(ckpt))})")
            except Exception as e:  # noqa: BLE001 (any unusable checkpoint: warn and start over, never fail)
                ctx.warn(f"--resume: checkpoint {ckpt} not usable ({one_line(e, 200)}); training from the start")
                # a fresh trainer (and log): nothing of the failed load survives
                log_path.unlink(missing_ok=True)
                trainer = Trainer(g, train_views, cfg, log_path=log_path)
                trainer.extra_fingerprint = init_fingerprint(g, train_views)

    progress = make_progress(
        TextColumn("loss {task.fields[loss]}"),
        TextColumn("PSNR {task.fields[psnr]}"),
        TextColumn("{task.fields[count]} G"),
        (TextColumn("{task.fields[rate]} it/s"), KEEP_FIELD + 1),  # the current rate outlasts loss and PSNR
    )
    start_it = trainer.iteration
    rate = RecentRate()
    rate.update(start_it, time.perf_counter())
    with _DeferredInterrupt() as stop, progress:
        task = progress.add_task(f"train ({init}, {p.projection}, {device})", total=cfg.iterations, completed=start_it,
                                 loss="-", psnr="-", count=len(trainer.g), rate="-")

        def on_step(tr: Trainer, info: dict) -> None:
            if tr.iteration % p.log_every and tr.iteration != cfg.iterations:
                # the loss and PSNR live on the device: reading them every iteration would sync
                progress.update(task, completed=tr.iteration)
            else:
                per_s = rate.update(tr.iteration, time.perf_counter())
                progress.update(task, completed=tr.iteration, loss=f"{float(tr.ema.loss):.4f}",
                                psnr=f"{float(tr.ema.psnr):.2f}", count=len(tr.g),
                                rate="-" if per_s is None else f"{per_s:.1f}")
            if stop.requested:
                console.print(f"interrupted: checkpoint at iteration {tr.iteration} -> {escape(str(ckpt))}; "
                              "rerun with --resume to continue")
                raise KeyboardInterrupt

        try:
            trainer.train(on_step=on_step, checkpoint_path=ckpt)
        except OSError as e:
            if ckpt is None or e.filename != str(ckpt):
                raise
            # the trainer's checkpoint (full disk, lost permission): one line naming the file
            raise PanoError(ckpt, e.strerror or one_line(e, 200)) from e

    final = trainer.final_gaussians()
    diverged = nonfinite_problem(final)
    if diverged:  # never a result: evaluate, export and the report would take NaNs for a model
        raise PanoError(ctx.out_dir.parent / "train",
                        f"training diverged after {trainer.iteration} iterations: {diverged}; nothing was kept "
                        "(lower the learning rates or loss weights)")
    save_ply(ctx.out_dir / "point_cloud.ply", final)
    if trainer.appearance is not None:  # for inspection: what exposure the model saw per panorama
        (ctx.out_dir / "appearance.json").write_text(json.dumps(trainer.appearance.as_dict(), indent=1))
    with open(log_path, "w") as f:  # the whole run's records, also across a resume
        for rec in trainer.records:
            f.write(json.dumps(rec) + "\n")
    final_psnr = trainer.mean_psnr()
    if ckpt is not None and ckpt.is_file():
        ckpt.unlink()  # finished: the artifact supersedes the checkpoint
    nonfinite = int(trainer.nonfinite_steps)
    if nonfinite:
        ctx.warn(f"{nonfinite} iterations had non-finite gradients (zeroed)")
    return TrainOutput(
        ply="point_cloud.ply",
        log="train_log.jsonl",
        num_gaussians=len(final),
        iterations=trainer.iteration,
        train_seconds=round(trainer.train_seconds, 3),
        kernel_build_seconds=None if kernel_build_s is None else round(kernel_build_s, 3),
        resolution=(height, 2 * height),
        sh_degree=final.sh_degree,
        init=init,
        projection=p.projection,
        crops=None if rig is None else CropRig.of(rig),
        train_images=len(train_views),
        layout_reg=p.layout_reg,
        backend=_backend_name(p.backend, device),
        device=device,
        final_train_psnr=final_psnr,
        preset=p.preset,
        lambda_layout=cfg.loss.lambda_layout if p.layout_reg else 0.0,
        extent=cfg.extent,
        resumed_from=resumed_from,
        step_seconds=None if trainer.part_seconds is None else {
            k: round(v, 3) for k, v in trainer.part_seconds.items()},
        appearance="appearance.json" if trainer.appearance is not None else None,
        # lambda_layout and coverage_height are settled by make_config (view count, height), the
        # background by the trainer ("mean": its images' mean colour)
        settings={**p.values_used(), "lambda_layout": cfg.loss.lambda_layout, "coverage_height": cfg.loss.coverage_height,
                  "background": list(trainer.background)},
    )


def build_kernel_first(backend: str | None, device: str) -> float | None:
    """Load the C++ CPU kernel before training, building it if this machine has no build yet, so
    that its one-time build is a step of its own, not training time (the report's seconds, the
    progress bar's rate); returns the build's seconds, None when nothing was built."""
    from runtime.console import console

    if device != "cpu" or backend not in (None, "cpp"):
        return None
    from splatting import raster_cpp

    if raster_cpp.is_built():
        return None
    console.print("train: compiling the C++ CPU kernel (once per machine; not counted as training)...")
    t0 = time.perf_counter()
    built = raster_cpp.load() is not None
    seconds = time.perf_counter() - t0
    console.print(f"train: C++ kernel {'built' if built else 'not built (the torch backend trains)'} "
                  f"in {seconds:.1f} s")
    return seconds


def resolve_device(requested: str, field: str) -> str:
    """`auto|cpu|cuda` to a torch device name; CUDA asked for on a machine without it is bad input
    (exit 2), not a silent CPU run of a GPU-sized preset."""
    if requested == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if requested == "cuda" and not torch.cuda.is_available():
        raise PanoError(field, "cuda asked for, but torch sees no CUDA device here (use auto or cpu)")
    return requested


def _backend_name(requested: str | None, device: str = "cpu") -> str:
    if requested:
        return requested
    if device == "cuda":
        from splatting import raster_triton

        return "cuda" if raster_triton.unavailable_reason(torch.device("cuda")) is None else "torch"
    try:
        from splatting import raster_cpp

        return "cpp" if raster_cpp.load() is not None else "torch"
    except Exception:  # noqa: BLE001 (the name is informative only)
        return "torch"
