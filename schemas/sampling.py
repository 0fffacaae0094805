"""Artifact of the `sampling` stage: the layout box sampled into a point cloud."""

from __future__ import annotations

from pydantic import BaseModel, Field

from schemas.cloud import CloudFiles


class SamplingOutput(BaseModel):
    cloud: CloudFiles
    density_per_m2: float
    mesh_glb: str | None = Field(default=None, description="room.glb: the extruded floor plan, for viewing.")
    points_per_surface: dict[str, int] = Field(description="wall / floor / ceiling point counts.")
