"""Artifact of the `sampling` stage: the layout box sampled into a point cloud."""

from __future__ import annotations

from pydantic import BaseModel, Field

from schemas.cloud import CloudFiles


class SamplingOutput(BaseModel):
    cloud: CloudFiles
    density_per_m2: float
    mesh_glb: str | None = Field(default=None, description="room.glb: the extruded floor plan, for viewing.")
    points_per_surface: dict[str, int] = Field(description="wall / floor / ceiling point counts.")
    labels: str | None = Field(
        default=None,
        description="labels.npz: per point surface (0 wall, 1 floor, 2 ceiling), room index, colouring view "
        "index into `views`, and `seen` (False: no train view had a clear line of sight).",
    )
    unseen_points: int = Field(
        default=0, ge=0, description="Points no train view sees (coloured from the nearest)."
    )
    points_per_view: dict[str, int] = Field(
        default_factory=dict, description="Points coloured from each train view."
    )
