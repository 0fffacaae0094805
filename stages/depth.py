"""depth: one depth map per train view, from a supplied file or an ONNX model.

Sources, in order of preference (`prefer` swaps the first two):
1. a supplied file, `scene.depth_path(view)`: depth/<view>.png (uint16
   millimetres, 0 = invalid) or .npy (float metres), distance along the ray,
   any 2:1 size;
2. an ONNX model (`model`), run under the contract in depthnet/runner.py:
   a 360° model on the panorama, or a perspective model on six cube faces;
3. none: the view gets no depth (a warning); with no file and no model for
   any train view the stage is skipped.

Each view's map is written as depth/<view>.npy, float32 [H,W], NaN where
invalid: 0, NaN, Inf, negative, or (metric) nearer than `near_limit` / beyond
`far_limit`. Model outputs keep their kind (metric, relative, disparity);
`align` fixes the scale. Test views are never read (they are for evaluation).
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from runfs.errors import PanoError
from runfs.limits import load_npy, read_image
from pipeline.stage import StageContext
from schemas.depth import DepthOutput, ViewDepth
from schemas.scene import Scene

Output = DepthOutput


class Params(BaseModel):
    model_config = ConfigDict(extra="forbid")

    model: Path | None = Field(
        default=None,
        description="ONNX depth model; a relative path is tried from the working folder, then the scene.",
    )
    output: Literal["metric", "relative", "disparity"] = Field(
        default="metric", description="What the model outputs."
    )
    normalization: Literal["unit", "imagenet"] = "unit"
    input_size: tuple[int, int] | None = Field(default=None, description="(H, W) fed to the model.")
    multiple_of: int = Field(
        default=1, ge=1, description="Input sides a multiple of this (14: Depth Anything)."
    )
    max_height: int = Field(default=512, ge=8, description="Model input height cap when its size is dynamic.")
    projection: Literal["equirect", "cubemap"] = Field(
        default="equirect", description="equirect: 360° model; cubemap: perspective model on six cube faces."
    )
    face_size: int = Field(default=256, ge=8)
    face_fov_deg: float = Field(default=100.0, ge=90.0, lt=170.0)
    perspective_axis: Literal["z", "ray"] = "z"
    prefer: Literal["file", "model"] = Field(
        default="file", description="Which source wins when a view has both."
    )
    output_height: int | None = Field(
        default=None, ge=8, description="Height of the stored model maps; default min(image height, 512)."
    )
    near_limit: float = Field(default=0.05, ge=0, description="Metric depth below this (m) is invalid.")
    far_limit: float = Field(default=100.0, gt=0, description="Metric depth beyond this (m) is invalid.")
    min_valid_fraction: float = Field(
        default=0.05, ge=0, le=1, description="Warn below this share of valid pixels."
    )
    threads: int = Field(default=2, ge=1, description="onnxruntime intra-op threads on CPU.")
    providers: list[str] | None = Field(
        default=None, description="onnxruntime providers; None: CUDA when available, else CPU."
    )

    def contract(self):
        from depthnet.runner import DepthContract

        return DepthContract(
            output=self.output,
            normalization=self.normalization,
            input_size=self.input_size,
            multiple_of=self.multiple_of,
            max_height=self.max_height,
            projection=self.projection,
            face_size=self.face_size,
            face_fov_deg=self.face_fov_deg,
            perspective_axis=self.perspective_axis,
        )


def skip_reason(scene: Scene, params: Params) -> str | None:
    if params.model:
        return None
    if any(scene.depth_path(v) is not None for v in scene.manifest.train_views()):
        return None
    return "no depth files (depth/<view>.png or .npy) and no depth.model"


# ----------------------------------------------------------------------------- pure helpers


def read_depth_file(path: str | Path) -> np.ndarray:
    """A supplied depth map in metres along the ray, float32 [H,W]; NaN where the file says invalid."""
    path = Path(path)
    if path.suffix.lower() == ".png":
        raw = read_image(path, what="depth map")
        if raw is None:
            raise PanoError(path, "unreadable depth PNG")
        if raw.dtype != np.uint16 or raw.ndim != 2:
            ch = 1 if raw.ndim == 2 else raw.shape[2]
            raise PanoError(
                path, f"depth PNG must be 16-bit single-channel millimetres, got {raw.dtype} x{ch}"
            )
        depth = raw.astype(np.float32) / 1000.0
        depth[raw == 0] = np.nan
    elif path.suffix.lower() == ".npy":
        depth = load_npy(path, pixels=True)
        if depth.ndim == 3 and depth.shape[-1] == 1:
            depth = depth[..., 0]
        if depth.ndim != 2 or not np.issubdtype(depth.dtype, np.number):
            raise PanoError(
                path, f"depth .npy must be a numeric [H,W] array, got {depth.dtype} {list(depth.shape)}"
            )
        depth = depth.astype(np.float32)
    else:
        raise PanoError(path, "depth file must be .png (uint16 mm) or .npy (float metres)")
    h, w = depth.shape
    if w != 2 * h:
        raise PanoError(path, f"depth map is {w}x{h} (width x height); expected a 2:1 equirectangular map, "
                              f"e.g. {2 * h}x{h}")
    if h < 4:
        raise PanoError(path, f"depth map is {w}x{h}; too small (at least 8x4)")
    return depth


def mask_invalid(values: np.ndarray, kind: str, near: float = 0.0, far: float = np.inf) -> np.ndarray:
    """NaN where a value cannot be used: non-finite anywhere; <= 0 for metric depth and disparity;
    outside [near, far] for metric depth."""
    v = np.asarray(values, dtype=np.float32).copy()
    bad = ~np.isfinite(v)
    if kind in ("metric", "disparity"):
        bad |= v <= 0
    if kind == "metric":
        bad |= (v < near) | (v > far)
    v[bad] = np.nan
    return v


# ----------------------------------------------------------------------------- stage glue


def run(ctx: StageContext[Params]) -> DepthOutput:
    from panogeom.images import read_rgb

    p = ctx.params
    scene = ctx.scene
    out = ctx.out_dir / "depth"
    out.mkdir(parents=True, exist_ok=True)
    model = None
    if p.model:
        from depthnet.runner import OnnxDepthModel

        model = OnnxDepthModel(
            p.model, p.contract(), threads=p.threads, providers=p.providers
        )

    views = scene.manifest.train_views()
    results: list[ViewDepth] = []
    for view in ctx.track(views, "depth", total=len(views)):
        file = scene.depth_path(view)
        use_file = file is not None and (model is None or p.prefer == "file")
        info: dict = {}
        if use_file:
            values, kind, source = read_depth_file(file), "metric", "file"
        elif model is not None:
            rgb = read_rgb(scene.image_path(view))
            values, info = _run_model(model, rgb, p)
            kind, source = p.output, "model"
        else:
            ctx.warn(f"view {view.name}: no depth file and no model; it gets no depth")
            continue
        values = mask_invalid(values, kind, p.near_limit, p.far_limit)
        valid = float(np.isfinite(values).mean())
        if valid < p.min_valid_fraction:
            ctx.warn(f"view {view.name}: only {valid:.1%} of the depth pixels are valid")
        np.save(out / f"{view.name}.npy", values.astype(np.float32))
        results.append(
            ViewDepth(
                view=view.name,
                depth=f"depth/{view.name}.npy",
                kind=kind,
                source=source,
                valid_fraction=valid,
                **info,
            )
        )
    if not results:
        raise PanoError(scene.root, "no train view has depth (no depth files, no depth.model)")
    return DepthOutput(views=results)


def _run_model(model, rgb: np.ndarray, p: Params) -> tuple[np.ndarray, dict]:
    """The model's map at the stored size, and what to record about the run."""
    from depthnet.cubemap import run_cubemap
    from depthnet.runner import run_equirect

    oh = p.output_height or min(rgb.shape[0], 512)
    hw = (oh, 2 * oh)
    info = {"model_input": model.input_hw(rgb.shape[:2])}
    if p.projection == "cubemap":
        values, faces = run_cubemap(model, rgb, hw)
        return values, {**info, **faces}
    return run_equirect(model, rgb, hw), info
