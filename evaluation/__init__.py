"""Evaluation: image and depth metrics, the HTML/Markdown report, ablation and sweep
experiments, and fly-through videos (docs/evaluation.md)."""

from evaluation.metrics import (
    LpipsUnavailable,
    depth_metrics,
    load_lpips,
    psnr,
    ssim,
    ws_psnr,
)

__all__ = ["psnr", "ssim", "ws_psnr", "depth_metrics", "load_lpips", "LpipsUnavailable"]
