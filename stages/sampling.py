"""sampling: the merged floor plan extruded from floor to ceiling, sampled into the layout point cloud
(each point with its plane's normal, into the room, and its initial position u0), coloured from the
training panoramas, and the room as a mesh (room.glb). The geometry is `floorplan.box_sampling`'s;
see docs/floorplan.md.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field

from floorplan.box_sampling import (
    choose_views,
    colour_points,
    room_mesh,
    sample_rooms,
    surface_areas,
    view_regions_from_layout,
)
from panogeom.images import read_rgb
from panogeom.surfaces import SURFACE_NAMES
from runfs.errors import PanoError
from runtime.stage import StageContext
from schemas.sampling import SamplingOutput
from schemas.scene import Scene
from schemas.stage_params import StageParams
from schemas.union import UnionOutput
from stages.cloud_io import write_cloud

Output = SamplingOutput


class Params(StageParams):
    density: float = Field(
        default=400.0,
        gt=0,
        le=1e6,
        description="Points per m^2 on every surface (400: 5 cm spacing, ~36k points for a 5x4x2.8 m room).",
    )
    jitter: bool = Field(
        default=True, description="Jitter each grid point inside its cell (stratified sampling)."
    )
    surfaces: list[Literal["wall", "floor", "ceiling"]] = Field(
        default=["wall", "floor", "ceiling"], min_length=1, description="Which surfaces to sample."
    )
    seed: int = Field(
        default=0, ge=0, le=2**32 - 1, description="Random seed of the jitter (same seed, same cloud).")
    visibility_eps: float = Field(
        default=1e-3,
        gt=0,
        description="Wall points are pulled this far into the room for the line-of-sight test (m).",
    )
    view_margin: float = Field(
        default=0.02,
        ge=0,
        description="A view's own floor polygon is grown by this (m) when deciding what it sees (layout noise).",
    )
    export_mesh: bool = Field(
        default=True,
        description="Write room.glb (the extruded floor plan, y up as glTF defines) for viewing."
    )
    max_points: int = Field(default=5_000_000, gt=0, description="Refuse to write more points than this.")


def skip_reason(scene: Scene, params: Params) -> str | None:
    return None


def run(ctx: StageContext) -> SamplingOutput:
    params: Params = ctx.params
    union: UnionOutput = ctx.inputs["union"].data
    if not union.rooms:
        raise PanoError(ctx.inputs["union"].dir / "artifact.json", "the floor plan has no rooms to sample")
    rooms = union.rooms
    areas = surface_areas(rooms)
    expected = params.density * sum(areas[s] for s in params.surfaces)
    if expected > params.max_points:
        raise PanoError(
            "params.density",
            f"{params.density:g} points/m^2 over {sum(areas.values()):.0f} m^2 gives ~{expected:.0f} points "
            f"(> max_points {params.max_points})",
        )
    s = sample_rooms(rooms, density=params.density, seed=params.seed, jitter=params.jitter,
                     surfaces=tuple(params.surfaces))

    # Colour from the train panoramas only: test views are held out.
    train = ctx.scene.manifest.train_views()
    centres = np.array([v.position for v in train])
    layout_in = ctx.inputs.get("layout")
    regions = view_regions_from_layout(layout_in.data if layout_in else None, train, params.view_margin)
    best, seen = choose_views(s.points, s.normals, centres, rooms, eps=params.visibility_eps, view_regions=regions)
    if (~seen).any():
        ctx.warn(
            f"{int((~seen).sum())} of {len(seen)} layout points are seen by no train view; "
            "coloured from the nearest one"
        )
    poses, images = [], []
    for v in ctx.track(train, "sampling: colour from views", total=len(train)):
        path = ctx.scene.image_path(v)
        try:
            images.append(read_rgb(path))
        except ValueError as exc:
            raise PanoError(path, "unreadable image") from exc
        poses.append(v.pose_matrix)
    colors = colour_points(s.points, best, poses, images)

    ctx.out_dir.mkdir(parents=True, exist_ok=True)
    cloud = write_cloud(ctx.out_dir, s.points, colors, s.normals, s.points, np.ones(len(s.points), bool))
    np.savez(
        ctx.out_dir / "labels.npz",
        surface=s.surface,
        room=s.room,
        view=best.astype(np.int16),
        seen=seen,
        views=np.array([v.name for v in train]),
    )
    mesh_rel = None
    if params.export_mesh:
        mesh = room_mesh(rooms)
        if mesh is not None:
            # glTF is y up by specification: rotated 180° about x (a rotation: the winding stays)
            mesh.apply_transform(np.diag([1.0, -1.0, -1.0, 1.0]))
            mesh.export(ctx.out_dir / "room.glb", file_type="glb")
            mesh_rel = "room.glb"
    counts = {name: int((s.surface == k).sum()) for k, name in enumerate(SURFACE_NAMES)}
    return SamplingOutput(
        cloud=cloud,
        density_per_m2=params.density,
        mesh_glb=mesh_rel,
        points_per_surface=counts,
        labels="labels.npz",
        unseen_points=int((~seen).sum()),
        points_per_view={v.name: int((best == i).sum()) for i, v in enumerate(train)},
    )
