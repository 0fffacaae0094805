"""Evaluation: image and depth metrics, the HTML/Markdown report, ablation and sweep
experiments, and fly-through videos (docs/evaluation.md).

Import the modules themselves (`from evaluation.metrics import psnr`): the package imports
nothing, so the CLI lists its commands without loading torch.
"""
