"""Artifact of the `depth` stage: one depth map per view."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, Field


class ViewDepth(BaseModel):
    view: str
    depth: str = Field(description="[H,W] float32 .npy along the ray; NaN where invalid.")
    kind: Literal["metric", "relative", "disparity"]
    source: Literal["file", "model"]
    valid_fraction: float = Field(ge=0, le=1)
    model_input: tuple[int, int] | None = Field(
        default=None, description="(H, W) fed to the model (a cube face's side for cube faces)."
    )
    face_scales: list[float] | None = Field(
        default=None,
        description="Cube-face path: each face's fitted scale (front, right, back, left, up, down).",
    )
    face_shifts: list[float] | None = Field(
        default=None, description="Cube-face path: each face's fitted shift."
    )


class DepthOutput(BaseModel):
    views: list[ViewDepth]
