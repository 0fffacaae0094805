"""3DGS's adaptive density control as one object, in the shape of gsplat's strategies.

:class:`DensifyStrategy` owns its thresholds, its schedule and its state (the screen-space
gradient statistics): the trainer calls :meth:`DensifyStrategy.step_post_backward` once per
iteration, after the optimiser step, and takes back the model, a new one when the strategy
cloned, split or pruned. Between densifications it only accumulates statistics (no host sync);
the opacity reset (3DGS's, or Mip-Splatting's cap when the 3D filter is on) is part of it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from gaussians.densify import DensifyStats, densify_and_prune, gradient_scale, reset_opacity
from gaussians.mip_filter import filter_variance, reset_cap_logits, sampling_rate
from gaussians.model import Gaussians
from gaussians.optim import Adam

__all__ = ["DensifyStrategy"]


@dataclass
class DensifyStrategy:
    """Clone, split and prune every `every` iterations in [`start`, `stop`), from the statistics
    gathered since the last time; reset the opacities every `opacity_reset_every`. Sizes are in
    metres (× `extent` already applied by :meth:`from_config`)."""

    start: int
    stop: int
    every: int
    grad_threshold: float
    percent_dense: float
    extent: float
    min_opacity: float
    #: prune Gaussians larger than this (metres) / covering more than this screen radius (radians),
    #: from `size_prune_from` (None: after the first opacity reset)
    max_world_scale: float | None
    max_screen_radius: float | None
    size_prune_from: int | None
    max_gaussians: int | None
    opacity_reset_every: int
    mip_filter: bool
    mip_filter_variance: float
    mip_filter_keep_integral: bool
    stats: DensifyStats

    @classmethod
    def from_config(cls, cfg, g: Gaussians) -> DensifyStrategy:
        """The strategy a TrainConfig describes, with empty statistics for model `g`."""
        return cls(
            start=cfg.densify.densify_from, stop=cfg.densify.densify_until, every=cfg.densify.densify_every,
            grad_threshold=cfg.densify.densify_grad_threshold, percent_dense=cfg.densify.percent_dense, extent=cfg.extent,
            min_opacity=cfg.densify.min_opacity,
            max_world_scale=cfg.densify.max_world_scale * cfg.extent if cfg.densify.max_world_scale else None,
            max_screen_radius=cfg.densify.max_screen_radius, size_prune_from=cfg.densify.size_prune_from,
            max_gaussians=cfg.densify.max_gaussians, opacity_reset_every=cfg.densify.opacity_reset_every,
            mip_filter=cfg.render.mip_filter, mip_filter_variance=cfg.render.mip_filter_variance,
            mip_filter_keep_integral=cfg.render.mip_filter_keep_integral,
            stats=DensifyStats.zeros(len(g), dtype=g.means.dtype, device=g.means.device))

    def _prunes_by_size(self, it: int) -> bool:
        if self.size_prune_from is not None:
            return it >= self.size_prune_from
        return self.opacity_reset_every > 0 and it > self.opacity_reset_every

    def step_post_backward(self, g: Gaussians, opt: Adam, out, camera, it: int, views,
                           generator: torch.Generator) -> Gaussians:
        """After iteration `it`'s optimiser step: gather `out`'s (the render's) statistics, and on
        the schedule densify and reset. Returns the model to train on (a new object after
        densification, `g` otherwise). `views` give the sampling rates of Mip-Splatting's reset."""
        if it >= self.stop:
            return g
        self.stats.add(out.means2d.grad if out.means2d.requires_grad else None, out.visible, out.radii,
                       camera.pixel_scale[0], gradient_scale(camera))
        if it >= self.start and it % self.every == 0:
            by_size = self._prunes_by_size(it)
            res = densify_and_prune(
                g, opt, self.stats, grad_threshold=self.grad_threshold, percent_dense=self.percent_dense,
                extent=self.extent, min_opacity=self.min_opacity,
                max_world_scale=self.max_world_scale if by_size else None,
                max_screen_radius=self.max_screen_radius if by_size else None,
                max_gaussians=self.max_gaussians, generator=generator)
            g = res.gaussians
            self.stats = DensifyStats.zeros(len(g), dtype=g.means.dtype, device=g.means.device)
        if self.opacity_reset_every > 0 and it % self.opacity_reset_every == 0:
            self._reset_opacity(g, opt, views)
        return g

    def _reset_opacity(self, g: Gaussians, opt: Adam, views) -> None:
        if not self.mip_filter:
            reset_opacity(g, opt)
            return
        # clamp the opacity as drawn (Mip-Splatting's reset)
        rate = sampling_rate(g.means, [v.viewmat for v in views], [v.camera for v in views])
        cap = reset_cap_logits(g.log_scales, filter_variance(rate, self.mip_filter_variance))
        if not self.mip_filter_keep_integral:
            cap = torch.full_like(cap, math.log(0.01 / 0.99))
        g.opacity_logits.copy_(torch.minimum(g.opacity_logits, cap))
        opt.reset("opacity_logits")
