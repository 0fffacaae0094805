"""Artifact of the `depth` stage: one depth map per view."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, Field, model_validator

#: What each kind of depth map means, in the words the artifacts use.
DEPTH_MODELS = {
    "metric": "metric distance",
    "relative": "affine depth",
    "disparity": "affine inverse depth",
}


class ViewDepth(BaseModel):
    view: str
    depth: str = Field(description="[H,W] float32 .npy along the ray; NaN where invalid.")
    kind: Literal["metric", "relative", "disparity"]
    source: Literal["file", "model"]
    depth_model: Literal["metric distance", "affine depth", "affine inverse depth"] | None = Field(
        default=None,
        description="The model of depth the values follow: metric distance (metres; align fits one global "
        "scale), affine depth (s*d + t) or affine inverse depth (1/d = s*v + t, Depth Anything; align fits "
        "s and t per view). Derived from `kind`.",
    )
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


    @model_validator(mode="after")
    def _name_the_depth_model(self):
        if self.depth_model is None:
            self.depth_model = DEPTH_MODELS[self.kind]
        elif self.depth_model != DEPTH_MODELS[self.kind]:
            raise ValueError(f"depth_model {self.depth_model!r} contradicts kind {self.kind!r}")
        return self


class DepthOutput(BaseModel):
    views: list[ViewDepth]
    model: str | None = Field(default=None, description="The ONNX model that ran (None: files only).")
    network: str | None = Field(
        default=None, description="The network the model's metadata names (e.g. Depth Anything V2 (vits))."
    )
    contract: dict | None = Field(
        default=None, description="The contract the model ran under (settings, model metadata, defaults)."
    )
