"""Artifact of the `align` stage: depth clouds scaled to the layout and merged with it."""

from __future__ import annotations

from pydantic import BaseModel, Field

from schemas.cloud import CloudFiles


class AlignOutput(BaseModel):
    cloud: CloudFiles = Field(description="Aligned depth points plus layout points (is_layout marks them).")
    scale: float = Field(description="Global scale applied to the depth (1 without a layout).")
    shift: float = Field(default=0.0, description="Shift fitted for relative depth/disparity.")
    inlier_share: float | None = None
    residual_m: float | None = Field(default=None, description="Median |aligned depth - layout depth| on inliers.")
    aligned_to_layout: bool
