"""Artifact of the `layout` stage: a metric room per view, in that view's camera frame."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, Field

Point2 = tuple[float, float]


class ViewLayout(BaseModel):
    view: str
    source: Literal["model", "json", "txt", "npy"] = Field(description="Where the boundaries came from.")
    boundaries: str = Field(description="[2,W] float32 .npy: ceiling and floor boundary latitudes (radians).")
    confidence: str | None = Field(default=None, description="[W] float32 .npy per-column confidence in [0,1].")
    floor_polygon: list[Point2] = Field(
        description="Floor outline in the camera frame, (x, z) metres, counter-clockwise seen from above."
    )
    camera_height: float = Field(gt=0, description="Camera above the floor (m): floor plane at camera y = +h.")
    ceiling_distance: float = Field(gt=0, description="Camera below the ceiling (m): ceiling at camera y = -d.")
    camera_height_assumed: bool = Field(description="True when 1.6 m was assumed (no height in scene.json).")


class LayoutOutput(BaseModel):
    views: list[ViewLayout]

    def view(self, name: str) -> ViewLayout:
        return next(v for v in self.views if v.view == name)
