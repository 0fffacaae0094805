"""Artifact of the `train` stage: the optimised Gaussians and how they were made."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, Field


class TrainOutput(BaseModel):
    ply: str = Field(description="point_cloud.ply in the standard 3DGS layout (see docs/training.md).")
    log: str = Field(description="train_log.jsonl: iteration, loss terms, PSNR, Gaussian count, wall time.")
    num_gaussians: int
    iterations: int
    train_seconds: float
    resolution: tuple[int, int] = Field(description="Training (height, width).")
    sh_degree: int
    init: Literal["random", "layout", "depth", "layout+depth"]
    projection: Literal["360", "cubemap"]
    layout_reg: bool
    backend: str
    final_train_psnr: float | None = None
    preset: Literal["fast", "paper", "quality"] = "fast"
    lambda_layout: float | None = Field(default=None, description="λ3 actually used (0 with layout_reg off).")
    extent: float | None = Field(default=None, description="Scene extent (m) scaling the position learning rate.")
    resumed_from: int | None = Field(default=None, description="Iteration a --resume continued from.")
    appearance: str | None = Field(default=None, description="appearance.json: each training panorama's "
                                                            "learned colour gain and bias (train.appearance).")
