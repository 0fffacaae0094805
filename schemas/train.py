"""Artifact of the `train` stage: the optimised Gaussians and how they were made."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, Field


class CropRig(BaseModel):
    """The perspective crops a `crops` or `cubemap` model was trained on (a splatting.PerspectiveRig):
    the evaluate stage renders the same crops, their size scaled with the panorama, and stitches them."""

    size: int = Field(description="Crop side in pixels at the training resolution.")
    fov_deg: float
    names: list[str]
    axes: list[list[list[float]]] = Field(description="Per crop, its x, y, z axes in the panorama camera frame.")

    @classmethod
    def of(cls, rig) -> CropRig:
        return cls(size=rig.size, fov_deg=rig.fov_deg, names=list(rig.names),
                   axes=[[list(a) for a in axes] for axes in rig.axes])

    def rig(self, size: int | None = None):
        """The splatting.PerspectiveRig, with crops of `size` pixels (default: as trained)."""
        import splatting

        axes = tuple(tuple(tuple(float(c) for c in a) for a in ax) for ax in self.axes)
        return splatting.PerspectiveRig(int(size or self.size), self.fov_deg, axes, tuple(self.names))


class TrainOutput(BaseModel):
    ply: str = Field(description="point_cloud.ply in the standard 3DGS layout (see docs/training.md).")
    log: str = Field(description="train_log.jsonl: iteration, loss terms, PSNR, Gaussian count, wall time.")
    num_gaussians: int
    iterations: int
    train_seconds: float = Field(description="Seconds of training iterations (without the kernel's build).")
    kernel_build_seconds: float | None = Field(
        default=None, description="Seconds compiling the C++ CPU kernel before training, on its first use on "
                                  "this machine (None: it was built already); not in train_seconds.")
    resolution: tuple[int, int] = Field(description="Training (height, width).")
    sh_degree: int
    init: Literal["random", "layout", "depth", "layout+depth"]
    projection: Literal["360", "crops", "cubemap"]
    crops: CropRig | None = Field(default=None, description="The crops of a crops/cubemap model (None: 360).")
    train_images: int | None = Field(
        default=None, description="Training images the iterations draw from: panoramas, or their crops; "
                                  "an iteration is one optimiser step on one of them.")
    layout_reg: bool
    backend: str
    device: str = Field(default="cpu", description="torch device the model was trained on (train.device).")
    final_train_psnr: float | None = None
    preset: Literal["fast", "paper", "quality"] = "fast"
    lambda_layout: float | None = Field(default=None, description="λ3 actually used (0 with layout_reg off).")
    extent: float | None = Field(default=None, description="Scene extent (m) scaling the position learning rate.")
    resumed_from: int | None = Field(default=None, description="Iteration a --resume continued from.")
    step_seconds: dict[str, float] | None = Field(
        default=None, description="Seconds spent in each part of the training step (render, losses, backward, "
                                  "optimiser, densify, log), summed over this run's iterations; CPU runs only "
                                  "(timing a GPU step would wait for the device at every part).")
    appearance: str | None = Field(default=None, description="appearance.json: each training panorama's "
                                                            "learned colour gain and bias (train.appearance).")
    settings: dict[str, Any] = Field(
        default_factory=dict, description="Every train setting's value used: as set, else the preset's, else the "
                                          "projection's default (the report shows these, not the unset nulls).")
