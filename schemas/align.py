"""Artifact of the `align` stage: depth clouds scaled to the layout and merged with it."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, Field

from schemas.cloud import CloudFiles


class KindFit(BaseModel):
    """One fit group: all metric views together, or one relative/disparity view (affine_fit per_view)."""

    kind: Literal["metric", "relative", "disparity"]
    depth_model: str = Field(
        default="",
        description="The model of depth assumed: metric distance (d = s*v), affine depth (d = s*v + t) or "
        "affine inverse depth (1/d = s*v + t); s and t below are its fitted parameters.",
    )
    views: list[str]
    scale: float = Field(
        description="Final scale (layout fit x ICP factor), as in depth = f(scale, shift, value)."
    )
    shift: float = Field(default=0.0, description="Final shift (relative depth: metres; disparity: 1/m).")
    layout_fit_scale: float = Field(description="Scale of the robust fit to the layout depth, before ICP.")
    icp_factor: float = Field(
        default=1.0, description="Depth multiplier found by the scale-only ICP (1 = none)."
    )
    icp_fitness: float | None = Field(
        default=None, description="Share of depth points within icp_max_distance."
    )
    icp_rmse_m: float | None = Field(
        default=None, description="RMS distance of those points to the layout cloud."
    )
    inlier_share: float | None = None
    residual_m: float | None = None
    num_pixels: int = Field(default=0, description="Pixels used by the layout fit (0: not fitted, scale 1).")


class AlignOutput(BaseModel):
    cloud: CloudFiles = Field(description="Aligned depth points plus layout points (is_layout marks them).")
    scale: float = Field(description="Global scale applied to the depth (1 without a layout).")
    shift: float = Field(default=0.0, description="Shift fitted for relative depth/disparity.")
    inlier_share: float | None = None
    residual_m: float | None = Field(
        default=None, description="Median |aligned depth - layout depth| on inliers."
    )
    aligned_to_layout: bool
    fits: list[KindFit] = Field(
        default_factory=list, description="Per fit group (scale/shift above: the largest)."
    )
