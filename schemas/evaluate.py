"""Artifact of the `evaluate` stage: metrics on the held-out views and render speed."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, Field, field_validator

from runfs.paths import safe_stem


class ViewMetrics(BaseModel):
    view: str

    @field_validator("view")
    @classmethod
    def _safe_name(cls, name: str) -> str:  # it names the report's image files, as it named the scene's
        return safe_stem(name)

    split: Literal["train", "test"]
    # None where the value is not finite (a render of NaNs, a perfect match): the report says it is missing
    psnr: float | None
    ssim: float | None
    ws_psnr: float | None = Field(description="PSNR with rows weighted by cos(latitude).")
    lpips: float | None = Field(default=None, description="None when LPIPS is unavailable (see lpips_reason).")
    psnr_colorfit: float | None = Field(
        default=None, description="PSNR after a per-channel least-squares gain and bias of the render to the "
                                  "ground truth: exposure and white balance factored out (not the raw metric).")
    ssim_colorfit: float | None = Field(default=None, description="SSIM after the same colour fit.")
    flat_psnr: float | None = Field(
        default=None, description="PSNR of a flat image of the training panoramas' mean colour (valid pixels): the "
                                  "floor a model must beat; None without posed training views.")
    flat_ssim: float | None = Field(default=None, description="SSIM of the same flat image.")
    depth_abs_rel: float | None = Field(default=None, description="Where the scene has ground-truth depth.")
    depth_rmse: float | None = Field(default=None, description="Metres, where the scene has ground-truth depth.")
    depth_valid_pixels: int | None = None
    render_seconds: float = Field(description="Wall time of this view's render.")
    gt: str = Field(description="Ground truth resized to the evaluation size (PNG).")
    render: str = Field(description="The rendered panorama (PNG).")
    error: str = Field(description="Per-pixel |render − gt| colour map (PNG).")
    depth: str = Field(description="Rendered expected depth, colour mapped (PNG).")
    depth_npy: str = Field(description="Rendered expected depth in metres, float32 [H,W] (.npy).")
    mask: str | None = Field(default=None, description="The pixels left out of every metric: the view's mask "
                                                       "file and/or the nadir cap; None = all pixels used.")


class EvaluateOutput(BaseModel):
    views: list[ViewMetrics]
    mean: dict[str, float | None] = Field(
        description="Metric -> mean over the evaluated views (psnr, ssim, ws_psnr, and lpips / depth_* where available)."
    )
    csv: str = Field(description="metrics.csv: one row per view plus a 'mean' row.")
    split: Literal["test", "train"] = Field(
        description="'test' normally; 'train' when the scene has no test views (then the numbers are fit, not generalisation)."
    )
    on_train_views: bool = Field(description="True when evaluated on training views for lack of test views.")
    resolution: tuple[int, int] = Field(description="Evaluation (height, width).")
    lpips_available: bool
    lpips_reason: str | None = Field(default=None, description="Why LPIPS is unavailable, when it is.")
    lpips_net: str | None = None
    fps: float = Field(description="Median frames per second of a full-panorama render at `resolution` "
                                   "(pose in, image on the device out; the download is not timed).")
    fps_repeats: int
    backend: str = Field(description="Splatting backend used for rendering.")
    device: str
    threads: int = Field(description="torch.get_num_threads() while rendering.")
    num_gaussians: int
    stitched: str | None = Field(
        default=None, description="How the test panoramas were made when the model was trained on crops: "
                                  "stitched from rendered crops (e.g. '8 crops of 120°, 64 px'); None = rendered directly.")
