"""layout: a metric room per view, from a supplied layout file or a
HorizonNet-compatible ONNX model (docs/layout.md).

Per view (train and test views alike; `union` uses the train ones):
1. a supplied file, `scene.layout_path(view)` — HorizonNet JSON, corner .txt
   or [2,W] .npy latitudes — wins over the model;
2. else the layout model (`model`: a known name, a .pth or an .onnx; by default a known layout
   model in the user's model cache), on the image resized to 512x1024 and turned into its room's
   Manhattan frame (`align`, layoutnet.alignment); the room is turned back into the view's frame;
3. else the view is left out (with a warning for a train view).
The camera height comes from scene.json, else 1.6 m (HorizonNet's
convention) with a warning. Writes `<view>.boundaries.npy` (the fitted room's
[2,W] latitudes at the image's width), `<view>.confidence.npy` ([W]) and, for
model/.npy sources, `<view>.raw_boundaries.npy` (the source's own boundaries). The rooms are
`layoutnet.rooms`'.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field

from layoutnet import postprocess as pp
from layoutnet.alignment import Alignment
from layoutnet.formats import read_layout
from layoutnet.rooms import room_from_model, room_from_supplied
from models.store import fetch_hint, model_label
from runfs.errors import PanoError
from runfs.limits import read_image
from runtime.stage import Loaded, StageContext
from schemas.layout import LayoutAlignment, LayoutOutput, PoseRescale, ViewLayout
from schemas.scene import MAX_CAMERA_HEIGHT, MIN_CAMERA_HEIGHT, Scene, View
from schemas.stage_params import StageParams

Output = LayoutOutput


class Params(StageParams):
    model: str | Path | None = Field(
        default=None,
        description="Layout model: a name from `pano-pipe models list` (get it with `pano-pipe models fetch "
        "NAME`), a HorizonNet checkpoint .pth (exported to ONNX on first use) or a HorizonNet-compatible "
        ".onnx; a relative path is tried from the working folder, then the scene folder. None: a known "
        "layout model in the model cache, for views without layout files; 'none': layout files only.",
    )
    align: Literal["auto", "lines", "off"] = Field(
        default="auto",
        description="Turn each panorama into its room's Manhattan frame before the model (HorizonNet is "
        "trained on such panoramas) and the room back: auto (gravity from the scene.json pose where given, "
        "the yaw from line segments), lines (gravity too from line segments), off (panoramas are aligned).",
    )
    max_tilt_deg: float = Field(
        default=30.0, gt=0, le=60, description="Largest camera tilt the alignment looks for (degrees).")
    providers: list[str] | None = Field(
        default=None, description="onnxruntime providers; None: CUDA when available, else CPU."
    )
    threads: int = Field(default=2, ge=1, description="onnxruntime intra-op threads on CPU.")
    tta: bool = Field(default=False, description="Average the model over a flip and three circular rolls.")
    mode: pp.Mode = Field(
        default=pp.DEFAULT_MODE,
        description="Wall fitting of boundaries (model or .npy): Manhattan (HorizonNet), a cuboid, or "
        "walls at any angle (Atlanta). Corner files (.json/.txt) are used as given.",
    )
    default_camera_height: float = Field(
        default=pp.DEFAULT_CAMERA_HEIGHT, ge=MIN_CAMERA_HEIGHT, le=MAX_CAMERA_HEIGHT,
        description="Camera height (m) where scene.json has none."
    )
    wall_source: pp.WallSource = Field(
        default=pp.DEFAULT_WALL_SOURCE, description="Which boundary places the walls (both: the mean of the two distances)."
    )
    peak_r: float = Field(
        default=pp.PEAK_R, gt=0, lt=1, description="Corner NMS window, a fraction of the width x2."
    )
    peak_min: float = Field(default=pp.PEAK_MIN, ge=0, lt=1, description="Minimum corner probability.")
    splits: Literal["all", "train"] = Field(
        default="train", description="Which views get a layout: train (all the pipeline uses) or all.")


def _has_source(scene: Scene, view: View) -> bool:
    return scene.layout_path(view) is not None



def _views_without_files(scene: Scene, params: Params) -> list[View]:
    return [v for v in selected_views(scene, params) if not _has_source(scene, v)]


def resolve_params(scene: Scene, params: Params) -> Params:
    """`model` → the ONNX file to run (models.resolve_model); None picks a known layout model from
    the user's cache when some view has no layout file (none there: stays None)."""
    from models.store import cached_model, ensure_onnx, resolve_model

    value = params.model
    if value is None:
        if not _views_without_files(scene, params):
            return params
        entry = cached_model("layout")
        return params.model_copy(update={"model": ensure_onnx(entry)}) if entry else params
    if isinstance(value, str) and value.strip().lower() == "none":
        return params.model_copy(update={"model": None})
    return params.model_copy(update={"model": resolve_model(value, "layout", search=(scene.root,))})


def skip_reason(scene: Scene, params: Params) -> str | None:
    if params.model is not None:
        return None
    if any(_has_source(scene, v) for v in selected_views(scene, params)):
        return None
    return f"no layout source: no layout files and no layout model; {fetch_hint('layout')}"


def run_reason(scene: Scene, params: Params) -> str:
    missing = _views_without_files(scene, params)
    if not missing:
        return "layout files for every view"
    if params.model is None:
        return f"{len(missing)} view(s) without layout files are left out ({fetch_hint('layout')})"
    return f"model {model_label(params.model)} for {len(missing)} view(s) without layout files"


def hint(scene: Scene, params: Params) -> str | None:
    """One line for `status` and the run header: the command that gets a layout model, when a
    train view has neither a layout file nor a model."""
    if params.model is not None:
        return None
    missing = [v for v in _views_without_files(scene, params) if v.split == "train"]
    if not missing:
        return None
    return (f"layout: {len(missing)} train view(s) have no layout file and no layout model is set or "
            f"cached; {fetch_hint('layout')}")



def selected_views(scene: Scene, params: Params) -> list[View]:
    return [v for v in scene.views if params.splits == "all" or v.split == "train"]


def _image_size(path: Path) -> tuple[int, int]:
    img = read_image(path)
    if img is None:
        raise PanoError(path, "unreadable image")
    return img.shape[0], img.shape[1]


def wall_fit(p: Params) -> dict:
    """How walls are fitted to boundaries (`layoutnet.rooms`' keywords) from the stage's settings."""
    return {"mode": p.mode, "wall_source": p.wall_source, "peak_r": p.peak_r, "peak_min": p.peak_min}


def _alignment_record(a: Alignment | None) -> LayoutAlignment | None:
    if a is None:
        return None
    return LayoutAlignment(rotation=[[float(x) for x in row] for row in a.rotation], yaw_deg=a.yaw_deg,
                           tilt_deg=a.tilt_deg, gravity=a.gravity, segments=a.segments, inliers=a.inliers)


# ----------------------------------------------------------------------------- the stage
def run(ctx: StageContext[Params]) -> LayoutOutput:
    from panogeom.images import read_rgb

    scene = ctx.scene
    params = resolve_params(scene, ctx.params)  # already resolved when the engine runs it: a no-op
    model = None
    model_path = None
    if params.model is not None:
        from layoutnet.inference import LayoutModel

        model_path = Path(params.model)
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
                got = room_from_supplied(sup, h, width, **wall_fit(params))
            except ValueError as e:
                raise PanoError(src, str(e)) from None
            source = sup.kind
        else:
            down = np.asarray(view.pose, dtype=np.float64)[1, :3] if view.pose is not None else None
            try:
                got = room_from_model(model, read_rgb(img_path), h, width, align=params.align,
                                      max_tilt_deg=params.max_tilt_deg, tta=params.tta, down=down, **wall_fit(params))
            except ValueError as e:  # e.g. NaN outputs
                raise PanoError(model_path, f"view {view.name}: unusable output: {e}") from None
            source = "model"
        room, raw, fitted, conf, alignment = got.room, got.raw, got.boundaries, got.confidence, got.alignment
        conf = np.asarray(conf, dtype=np.float32)
        for note in room.notes:
            ctx.warn(f"view {view.name}: {note}")

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
                alignment=_alignment_record(alignment),
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
    from models.store import known_name

    return LayoutOutput(views=out, model=str(model_path) if model_path else None,
                        model_name=known_name(model_path) if model_path else None,
                        poses_rescale=_rescale_poses(ctx, out))


def _rescale_poses(ctx: StageContext[Params], rooms: list[ViewLayout]) -> PoseRescale | None:
    """Poses the poses stage kept up to scale (scale_source none): their metres per unit, measured
    from the rooms' walls and the sparse points the views observe (layoutnet.pose_scale), for the
    later stages (complete_scene). Says what it did in one warning either way."""
    from layoutnet.pose_scale import scale_from_rooms
    from stages.poses import read_observations

    poses = ctx.input("poses")
    if poses is None or poses.data.scale_source != "none":
        return None
    data = poses.data
    seen = read_observations(poses.path(data.observations))[1] if data.observations else {}
    by_name = {v.name: v for v in ctx.scene.views}
    found = scale_from_rooms([(np.asarray(by_name[r.view].pose), np.asarray(r.floor_polygon), seen[r.view])
                              for r in rooms if r.view in seen and by_name[r.view].pose is not None])
    if found is None:
        ctx.warn("the poses have no metric scale (poses: scale_source none) and the rooms could not measure it: "
                 "the rooms are metric, the poses that place them are not")
        return None
    given = [v for v in data.views if v.given and v.pose is not None]
    anchor = np.asarray(given[0].pose)[:3, 3].tolist() if given else [0.0, 0.0, 0.0]
    views = [v.view for v in data.views if v.registered and not v.given]
    ctx.warn(f"the poses have no metric scale (poses: scale_source none): {found.scale:.4g} m per unit "
             f"± {100 * found.uncertainty:.2g} % measured from the rooms' walls ({found.votes} of {found.points} "
             "sparse points agree); the later stages see the poses scaled by it")
    return PoseRescale(scale=found.scale, uncertainty=found.uncertainty, anchor=anchor, views=views,
                       votes=found.votes, points=found.points)


def complete_scene(scene: Scene, artifact: Loaded) -> Scene:
    """The scene with the poses the layout stage made metric (LayoutOutput.poses_rescale) scaled."""
    fix = artifact.data.poses_rescale
    return scene if fix is None else scene.with_scaled_positions(fix.views, fix.scale, fix.anchor)
