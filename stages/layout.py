"""layout: a metric room per view, from a supplied layout file or a
HorizonNet-compatible ONNX model (docs/layout.md).

Per view (train and test views alike; `union` uses the train ones):
1. a supplied file, `scene.layout_path(view)` — HorizonNet JSON, corner .txt
   or [2,W] .npy latitudes — wins over the model;
2. else the ONNX model (`model`), on the image resized to 512x1024;
3. else the view is left out (with a warning for a train view).
The camera height comes from scene.json, else 1.6 m (HorizonNet's
convention) with a warning. Writes `<view>.boundaries.npy` (the fitted room's
[2,W] latitudes at the image's width), `<view>.confidence.npy` ([W]) and, for
model/.npy sources, `<view>.raw_boundaries.npy` (the source's own boundaries).
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from layoutnet import postprocess as pp
from layoutnet.formats import SuppliedLayout, read_layout
from runfs.errors import PanoError
from runfs.limits import read_image
from pipeline.stage import StageContext
from schemas.layout import LayoutOutput, ViewLayout
from schemas.scene import Scene, View

Output = LayoutOutput


class Params(BaseModel):
    model_config = ConfigDict(extra="forbid")

    model: Path | None = Field(
        default=None,
        description="HorizonNet-compatible ONNX model (pano-pipe export-layout-model makes one); a relative "
        "path is tried from the working folder, then the scene folder. None: supplied layout files only.",
    )
    providers: list[str] | None = Field(
        default=None, description="onnxruntime providers; None: CUDA when available, else CPU."
    )
    threads: int = Field(default=2, ge=1, description="onnxruntime intra-op threads on CPU.")
    tta: bool = Field(default=False, description="Average the model over a flip and three circular rolls.")
    mode: Literal["manhattan", "cuboid", "atlanta"] = Field(
        default="manhattan",
        description="Wall fitting of boundaries (model or .npy): Manhattan (HorizonNet), a cuboid, or "
        "walls at any angle (Atlanta). Corner files (.json/.txt) are used as given.",
    )
    default_camera_height: float = Field(
        default=pp.DEFAULT_CAMERA_HEIGHT, gt=0, description="Camera height (m) where scene.json has none."
    )
    wall_source: Literal["both", "ceiling", "floor"] = Field(
        default="both", description="Which boundary places the walls (both: the mean of the two distances)."
    )
    peak_r: float = Field(
        default=0.05, gt=0, lt=1, description="Corner NMS window, a fraction of the width x2."
    )
    peak_min: float = Field(default=0.05, ge=0, lt=1, description="Minimum corner probability.")
    splits: Literal["all", "train"] = Field(
        default="train", description="Which views get a layout: train (all the pipeline uses) or all.")


def _has_source(scene: Scene, view: View) -> bool:
    return scene.layout_path(view) is not None


def skip_reason(scene: Scene, params: Params) -> str | None:
    if params.model is not None:
        return None
    if any(_has_source(scene, v) for v in selected_views(scene, params)):
        return None
    return "no layout source: no layout/ files and no `layout.model` configured"


def selected_views(scene: Scene, params: Params) -> list[View]:
    return [v for v in scene.views if params.splits == "all" or v.split == "train"]


def _image_size(path: Path) -> tuple[int, int]:
    img = read_image(path)
    if img is None:
        raise PanoError(path, "unreadable image")
    return img.shape[0], img.shape[1]


# ----------------------------------------------------------------------------- pure helpers
def room_from_supplied(
    sup: SuppliedLayout, camera_height: float, params: Params
) -> tuple[pp.RoomLayout, np.ndarray | None]:
    """A supplied layout → (room, the source's boundaries or None for corner formats)."""
    if sup.boundaries is not None:
        room = pp.layout_from_boundaries(
            sup.boundaries,
            camera_height,
            mode=params.mode,
            wall_source=params.wall_source,
            peak_r=params.peak_r,
            peak_min=params.peak_min,
        )
        return room, sup.boundaries
    c = sup.corners
    if sup.ceiling_ratio is not None:
        ceiling = sup.ceiling_ratio * camera_height
    else:  # each corner's floor point fixes its distance, its ceiling point then the ceiling
        ceiling = pp.mean_percentile(camera_height * np.tan(c[:, 1]) / np.tan(-c[:, 2]))
    poly = pp.corners_to_polygon(c[:, 0], c[:, 1], c[:, 2], camera_height, ceiling)
    return pp.RoomLayout(poly, camera_height, float(ceiling), "corners"), None


def room_from_model(
    model, rgb: np.ndarray, camera_height: float, params: Params
) -> tuple[pp.RoomLayout, np.ndarray]:
    """Run the ONNX model on an RGB panorama ([H,W,3] in [0,1], any 2:1 size) and post-process."""
    x = cv2.resize(rgb, (1024, 512), interpolation=cv2.INTER_AREA if rgb.shape[0] > 512 else cv2.INTER_LINEAR)
    bounds, cor = model.predict(x, tta=params.tta)
    room = pp.layout_from_boundaries(
        bounds,
        camera_height,
        cor=cor,
        mode=params.mode,
        wall_source=params.wall_source,
        peak_r=params.peak_r,
        peak_min=params.peak_min,
    )
    return room, bounds


# ----------------------------------------------------------------------------- the stage
def run(ctx: StageContext[Params]) -> LayoutOutput:
    from panogeom.images import read_rgb

    scene, params = ctx.scene, ctx.params
    model = None
    model_path = None
    if params.model is not None:
        from layoutnet.inference import LayoutModel

        model_path = params.model  # the engine resolved it (pipeline.engine.Engine.params_for)
        model = LayoutModel(model_path, providers=params.providers, threads=params.threads)

    views = selected_views(scene, params)
    assumed: list[str] = []
    out: list[ViewLayout] = []
    for view in ctx.track(views, "layout", total=len(views)):
        src = scene.layout_path(view)
        if src is None and model is None:
            if view.split == "train":  # test views are expected to come bare
                ctx.warn(f"view {view.name}: no layout file and no layout model; left out")
            continue
        h = view.camera_height
        if h is None:
            h = params.default_camera_height
            assumed.append(view.name)
        img_path = scene.image_path(view)
        height, width = _image_size(img_path)
        if src is not None:
            sup = read_layout(src, width, height)
            try:
                room, raw = room_from_supplied(sup, h, params)
            except ValueError as e:
                raise PanoError(src, str(e)) from None
            source = sup.kind
        else:
            try:
                room, raw = room_from_model(model, read_rgb(img_path), h, params)
            except ValueError as e:  # e.g. NaN outputs
                raise PanoError(model_path, f"view {view.name}: unusable output: {e}") from None
            source = "model"
        for note in room.notes:
            ctx.warn(f"view {view.name}: {note}")

        fitted = pp.polygon_to_boundaries(room.polygon, room.camera_height, room.ceiling_distance, width)
        if raw is not None:
            conf = pp.column_confidence(raw, fitted)
            conf = pp.resample_boundaries(conf[None].astype(np.float64), width)[0].astype(np.float32)
        else:
            conf = np.ones(width, dtype=np.float32)
        np.save(ctx.out_dir / f"{view.name}.boundaries.npy", fitted.astype(np.float32))
        np.save(ctx.out_dir / f"{view.name}.confidence.npy", conf)
        raw_rel = None
        if raw is not None:
            raw_rel = f"{view.name}.raw_boundaries.npy"
            np.save(ctx.out_dir / raw_rel, np.asarray(raw, dtype=np.float32))
        out.append(
            ViewLayout(
                view=view.name,
                source=source,
                boundaries=f"{view.name}.boundaries.npy",
                confidence=f"{view.name}.confidence.npy",
                floor_polygon=[(float(x), float(z)) for x, z in room.polygon],
                camera_height=room.camera_height,
                ceiling_distance=room.ceiling_distance,
                camera_height_assumed=view.name in assumed,
                split=view.split,
                raw_boundaries=raw_rel,
                method=room.method,
            )
        )
    if assumed:
        ctx.warn(
            f"no camera_height in scene.json for {', '.join(assumed)}: assumed "
            f"{params.default_camera_height:g} m (HorizonNet's convention); the layout scale follows it"
        )
    if not out:
        raise PanoError(
            scene.root, "no view got a layout (no layout files for the selected views and no model)"
        )
    return LayoutOutput(views=out, model=str(model_path) if model_path else None)
