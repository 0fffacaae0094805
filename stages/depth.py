"""depth: one depth map per train view, from a supplied file or a depth model.

Sources, in order of preference (`prefer` swaps the first two):
1. a supplied file, `scene.depth_path(view)`: depth/<view>.png (uint16
   millimetres, 0 = invalid) or .npy (float metres), distance along the ray,
   any 2:1 size;
2. a model (`model`: a known name such as depth-anything-v2-small, a .pth
   exported on first use, or an .onnx; unset: a known model in the user's
   cache when a layout will be there to align it), run under the contract in
   depthnet/runner.py (settings, else the model's metadata): a 360° model on
   the panorama, or a perspective model on six cube faces;
3. none: the view gets no depth (a warning); with no file and no model for
   any train view the stage is skipped.

Each view's map is written as depth/<view>.npy, float32 [H,W], NaN where
invalid: 0, NaN, Inf, negative, or (metric) nearer than `near_limit` / beyond
`far_limit`. Model outputs keep their kind (metric distance, affine depth,
affine inverse depth), recorded in the artifact; `align` fits scale (and
shift). Test views are never read (they are for evaluation).
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field

from models.store import fetch_hint, model_label
from runfs.errors import PanoError
from runtime.stage import StageContext
from schemas.depth import DepthOutput, ViewDepth
from schemas.scene import Scene, View
from schemas.scene_loader import read_depth_file
from schemas.stage_params import StageParams

Output = DepthOutput


class Params(StageParams):
    model: str | Path | None = Field(
        default=None,
        description="Depth model: a name from `pano-pipe models list` (depth-anything-v2-small; get it with "
        "`pano-pipe models fetch NAME`), a Depth Anything V2 checkpoint .pth in the official layout "
        "(exported to ONNX on first use) or an .onnx; a relative path is tried from the working folder, "
        "then the scene folder. None: a known depth model in the model cache, for train views without "
        "depth files when the scene will have a layout to align it to; 'none': depth files only.",
    )
    output: Literal["metric", "relative", "disparity"] | None = Field(
        default=None,
        description="What the model outputs: metric (metres along the ray or axis), relative (depth up to "
        "scale and shift) or disparity (inverse depth up to scale and shift, Depth Anything). None: what "
        "the model's metadata records (pano-pipe's exports do), else metric.",
    )
    normalization: Literal["unit", "imagenet"] | None = Field(
        default=None, description="None: from the model's metadata, else unit ([0,1] RGB)."
    )
    input_size: tuple[int, int] | None = Field(default=None, json_schema_extra={"pixels": "hw"},
                                              description="(H, W) fed to the model.")
    multiple_of: int | None = Field(
        default=None, ge=1, description="Input sides a multiple of this (14: Depth Anything); None: from the "
        "model's metadata, else 1."
    )
    max_height: int = Field(default=512, ge=8, json_schema_extra={"pixels": "panorama_height"},
                            description="Model input height cap when its size is dynamic.")
    projection: Literal["equirect", "cubemap"] | None = Field(
        default=None,
        description="equirect: 360° model; cubemap: perspective model on six cube faces. None: from the "
        "model's metadata, else equirect."
    )
    face_size: int | None = Field(
        default=None, ge=8, json_schema_extra={"pixels": "square"},
        description="Cube face side (px) for a model of dynamic size; None: from the "
        "model's metadata, else 256."
    )
    face_fov_deg: float = Field(
        default=100.0, ge=90.0, lt=170.0,
        description="cubemap: field of view of a face (degrees); above 90 neighbouring faces overlap and "
                    "are blended.")
    perspective_axis: Literal["z", "ray"] = Field(
        default="z",
        description="cubemap: the model's depth is along the optical axis (z, most models) or the ray.")
    prefer: Literal["file", "model"] = Field(
        default="file", description="Which source wins when a view has both."
    )
    output_height: int | None = Field(
        default=None, ge=8, json_schema_extra={"pixels": "panorama_height"},
        description="Height of the stored model maps; default min(image height, 512)."
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

    def contract_overrides(self) -> dict:
        """The contract settings given here; the rest come from the model's metadata or the defaults."""
        from depthnet.runner import DepthContract

        return {k: v for k in DepthContract.model_fields if (v := getattr(self, k)) is not None}



def _views_without_files(scene: Scene) -> list[View]:
    return [v for v in scene.manifest.train_views() if scene.depth_path(v) is None]


def _layout_expected(scene: Scene, views: list[View]) -> bool:
    """Whether `views` will have a layout to fix an affine depth model's scale and shift: layout
    files for all of them, or a known layout model in the cache (what the layout stage then uses)."""
    from models.store import cached_model

    return all(scene.layout_path(v) is not None for v in views) or cached_model("layout") is not None


def resolve_params(scene: Scene, params: Params) -> Params:
    """`model` -> the ONNX file to run (models.resolve_model: a name, a .pth exported once, an .onnx).
    None picks a known depth model from the user's cache for train views without depth files, when
    a layout will be there to align its relative depth to (else align could not use it)."""
    from models.store import cached_model, ensure_onnx, resolve_model

    value = params.model
    if value is None:
        missing = _views_without_files(scene)
        if not missing or not _layout_expected(scene, missing):
            return params
        entry = cached_model("depth")
        return params.model_copy(update={"model": ensure_onnx(entry)}) if entry else params
    if isinstance(value, str) and value.strip().lower() == "none":
        return params.model_copy(update={"model": None})
    return params.model_copy(update={"model": resolve_model(value, "depth", search=(scene.root,))})


def skip_reason(scene: Scene, params: Params) -> str | None:
    if params.model:
        return None
    if any(scene.depth_path(v) is not None for v in scene.manifest.train_views()):
        return None
    return f"no depth files (depth/<view>.png or .npy) and no depth model; {fetch_hint('depth')}"


def run_reason(scene: Scene, params: Params) -> str:
    missing = _views_without_files(scene)
    if not missing:
        return "depth files for every train view"
    if params.model is None:
        return f"{len(missing)} train view(s) without depth files get no depth ({fetch_hint('depth')})"
    return f"model {model_label(params.model)} for {len(missing)} train view(s) without depth files"


def hint(scene: Scene, params: Params) -> str | None:
    """One line for `status` and the run header when train views have no depth and no model will run."""
    if params.model is not None:
        return None
    missing = _views_without_files(scene)
    if not missing:
        return None
    return (f"depth: {len(missing)} train view(s) have no depth file and no depth model is set or cached; "
            f"{fetch_hint('depth')}")


# ----------------------------------------------------------------------------- pure helpers


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

    scene = ctx.scene
    p = resolve_params(scene, ctx.params)  # already resolved when the engine runs it: a no-op
    out = ctx.out_dir / "depth"
    out.mkdir(parents=True, exist_ok=True)
    model = None
    if p.model:
        from depthnet.runner import OnnxDepthModel

        model = OnnxDepthModel(
            p.model, threads=p.threads, providers=p.providers, overrides=p.contract_overrides()
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
            kind, source = model.contract.output, "model"
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
    return DepthOutput(
        views=results,
        model=model_label(p.model) if model is not None else None,
        network=model.description.get("architecture") if model is not None else None,
        contract=model.contract.model_dump(mode="json") if model is not None else None,
    )


def _run_model(model, rgb: np.ndarray, p: Params) -> tuple[np.ndarray, dict]:
    """The model's map at the stored size, and what to record about the run."""
    from depthnet.cubemap import run_cubemap
    from depthnet.runner import run_equirect

    oh = p.output_height or min(rgb.shape[0], 512)
    hw = (oh, 2 * oh)
    info = {"model_input": model.input_hw(rgb.shape[:2])}
    if model.contract.projection == "cubemap":
        values, faces = run_cubemap(model, rgb, hw)
        return values, {**info, **faces}
    return run_equirect(model, rgb, hw), info
