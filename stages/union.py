"""union: the train views' floor plans moved into the world frame and merged into one floor plan
(floor_plan.json, floor_plan.png). The geometry is `floorplan.union`'s; see docs/floorplan.md.
"""

from __future__ import annotations

import json

from pydantic import Field

from floorplan.union import build_floor_plan, draw_floor_plan, room_shape
from runfs.errors import PanoError
from runtime.stage import StageContext
from schemas.layout import LayoutOutput
from schemas.scene import Scene
from schemas.stage_params import StageParams
from schemas.union import UnionOutput

Output = UnionOutput


class Params(StageParams):
    tolerance: float = Field(
        default=0.05, ge=0, description="Gaps and slivers narrower than 2x this (m) are closed / removed."
    )
    min_room_area: float = Field(
        default=0.5, ge=0, description="Components smaller than this (m^2) are dropped."
    )
    simplify: float = Field(
        default=0.002, ge=0, description="Douglas-Peucker tolerance (m) applied to the merged outline."
    )
    max_tilt_deg: float = Field(
        default=5.0, gt=0, description="Warn when a camera's up axis is tilted more than this from world -y."
    )
    drawing_dpi: int = Field(
        default=120, ge=30, le=600, description="Resolution of floor_plan.png (dots per inch).")


def skip_reason(scene: Scene, params: Params) -> str | None:
    return None  # runs whenever its required input (layout) exists


def plan_settings(p: Params) -> dict:
    """`floorplan.union.build_floor_plan`'s settings from the stage's."""
    return {"tolerance": p.tolerance, "min_room_area": p.min_room_area, "simplify": p.simplify,
            "max_tilt_deg": p.max_tilt_deg}


def run(ctx: StageContext) -> UnionOutput:
    params: Params = ctx.params
    layout: LayoutOutput = ctx.inputs["layout"].data
    have = {v.view: v for v in layout.views}
    train = ctx.scene.manifest.train_views()
    # Only train views: test views are held out for evaluation and must not shape the prior.
    layouts = []
    for v in ctx.track(train, "union: views", total=len(train)):
        if v.name not in have:
            ctx.warn(f"view {v.name}: no layout; left out of the floor plan")
            continue
        layouts.append(have[v.name])
    if not layouts:
        raise PanoError(
            ctx.scene.root / "scene.json", "no train view has a layout to build a floor plan from"
        )
    poses = {v.name: v.pose_matrix for v in train}
    rooms, per_view = build_floor_plan(layouts, poses, **plan_settings(params), warn=ctx.warn)

    ctx.out_dir.mkdir(parents=True, exist_ok=True)
    doc = {
        "rooms": [r.model_dump(mode="json") for r in rooms],
        "views": per_view,
        "tolerance": params.tolerance,
        "frame": "world (x, z) metres, y down; polygons counter-clockwise in (x, z)",
    }
    (ctx.out_dir / "floor_plan.json").write_text(json.dumps(doc, indent=1))
    draw_floor_plan(ctx.out_dir / "floor_plan.png", rooms, per_view, params.drawing_dpi)
    return UnionOutput(
        rooms=rooms,
        floor_plan="floor_plan.json",
        drawing="floor_plan.png",
        area_m2=float(sum(room_shape(r).area for r in rooms)),
    )
