"""Mip-Splatting's 3D smoothing filter (Yu et al., CVPR 2024, "Mip-Splatting: Alias-free 3D
Gaussian Splatting", section 5.1 and its official code's `compute_3D_filter`).

A Gaussian smaller than the training views' sampling interval is unconstrained in size: nothing
in the training images tells a 1 mm needle from a 1 cm one. Seen from a closer camera such
Gaussians become thin needles with gaps between them ("erosion"). The filter convolves every
Gaussian with an isotropic 3D Gaussian low-pass whose width is the sampling interval of the
training camera that samples it most finely:

    ν     = max over training cameras k that see the Gaussian of  f_k / d_k   (pixels per metre)
    Σ'    = Σ + (s / ν²) · I                   s = `variance` (the official code's 0.2)
    α'    = α · sqrt(det Σ / det Σ')           (the low-pass keeps the Gaussian's integral)

f_k is the camera's pixels per radian (W / 2π for an equirectangular panorama, fx for a pinhole)
and d_k the Gaussian's distance (a panorama) or depth z (a pinhole camera, as the official code).
A Gaussian no training camera sees gets the smallest rate of those seen (the official code's
choice). Σ and Σ + v·I share their eigenvectors, so the filter only changes the scales:
s_i' = sqrt(s_i² + v), and det Σ / det Σ' = Π s_i² / (s_i² + v).

`filtered(g, variance)` returns the Gaussians a renderer should draw, differentiable in g's
log scales and opacity logits, in the same raw parametrisation (log scales, opacity logits), so
the renderer, the PLY and every viewer need nothing new.
"""

from __future__ import annotations

import math
from dataclasses import replace

import torch
import torch.nn.functional as F

from gaussians.model import Gaussians

__all__ = ["DEFAULT_VARIANCE", "sampling_rate", "filter_variance", "filtered_log_scales", "filtered_opacity_logits",
           "filtered", "reset_cap_logits"]

#: The official code's `filter_3D = distance / focal * sqrt(0.2)`: the low-pass's variance, in
#: (sampling intervals)²
DEFAULT_VARIANCE = 0.2
#: A pinhole camera counts as seeing a Gaussian that projects within 15 % of its image's border
#: (the official code's margin) and lies in front of `near`
_SCREEN_MARGIN = 0.15


@torch.no_grad()
def sampling_rate(means: torch.Tensor, viewmats: list[torch.Tensor], cameras: list,
                  near: float = 0.05) -> torch.Tensor:
    """[N] the finest sampling rate (pixels per metre) at which any of the training cameras
    (`viewmats` world-to-camera [4,4], `cameras` splatting.EquirectCamera / PinholeCamera)
    sees each Gaussian centre `means` [N,3]. A panorama sees every point at its distance; a pinhole
    camera the points in front of `near` that project within its image (plus a 15 % margin)."""
    n = means.shape[0]
    rate = means.new_zeros(n)
    if n == 0:
        return rate
    for vm, cam in zip(viewmats, cameras):
        vm = vm.to(device=means.device, dtype=means.dtype)
        p = means @ vm[:3, :3].T + vm[:3, 3]
        if getattr(cam, "kind", None) == "equirect":
            d = torch.linalg.vector_norm(p, dim=1)
            r = (cam.width / (2.0 * math.pi)) / d.clamp_min(near)
        else:
            z = p[:, 2]
            zc = z.clamp_min(near)
            u = p[:, 0] / zc * cam.fx + cam.cx
            v = p[:, 1] / zc * cam.fy + cam.cy
            w, h = float(cam.width), float(cam.height)
            seen = ((z > near) & (u >= -_SCREEN_MARGIN * w) & (u <= (1 + _SCREEN_MARGIN) * w)
                    & (v >= -_SCREEN_MARGIN * h) & (v <= (1 + _SCREEN_MARGIN) * h))
            r = torch.where(seen, max(float(cam.fx), float(cam.fy)) / zc, torch.zeros_like(zc))
        rate = torch.maximum(rate, r)
    seen = rate > 0
    if bool(seen.any()) and not bool(seen.all()):
        rate = torch.where(seen, rate, rate[seen].min())
    elif not bool(seen.any()):
        rate.fill_(float("inf"))  # no camera sees anything: no filter
    return rate


def filter_variance(rate: torch.Tensor, variance: float = DEFAULT_VARIANCE) -> torch.Tensor:
    """[N] the 3D low-pass's variance (m²) for sampling rates `rate` (pixels per metre)."""
    return variance / rate.square()


def filtered_log_scales(log_scales: torch.Tensor, var: torch.Tensor) -> torch.Tensor:
    """log sqrt(s² + v) per axis ([N,3] log scales, [N] variances), differentiable in log_scales."""
    return 0.5 * torch.logaddexp(2.0 * log_scales, torch.log(var)[:, None].expand_as(log_scales))


def filtered_opacity_logits(opacity_logits: torch.Tensor, log_scales: torch.Tensor,
                            new_log_scales: torch.Tensor) -> torch.Tensor:
    """logit(α · r) with r = sqrt(det Σ / det Σ') = Π s_i / s_i', computed without forming α·r
    (which rounds to 1 for a large logit): logit(α r) = log α + log r − log(1 − α + α (1 − r))."""
    log_r = (log_scales - new_log_scales).sum(dim=1)
    one_minus_r = -torch.expm1(log_r)
    return (F.logsigmoid(opacity_logits) + log_r
            - torch.log(torch.sigmoid(-opacity_logits) + torch.sigmoid(opacity_logits) * one_minus_r))


def filtered(g: Gaussians, var: torch.Tensor, keep_integral: bool = True) -> Gaussians:
    """`g` with the 3D low-pass of variances `var` [N] applied: the same tensors except the log
    scales and opacity logits, which are functions of g's (gradients flow back to them).
    `keep_integral=False` widens without lowering the opacity (not Mip-Splatting's filter: an
    ablation that tells whether the opacity compensation is what leaves a thin Gaussian faint)."""
    ls = filtered_log_scales(g.log_scales, var)
    if not keep_integral:
        return replace(g, log_scales=ls)
    return replace(g, log_scales=ls, opacity_logits=filtered_opacity_logits(g.opacity_logits, g.log_scales, ls))


def reset_cap_logits(log_scales: torch.Tensor, var: torch.Tensor, max_opacity: float = 0.01) -> torch.Tensor:
    """[N] the largest raw opacity logit whose *filtered* opacity is at most `max_opacity`: the
    opacity reset of Mip-Splatting's code, which clamps the opacity as drawn (α · r ≤ m, so
    α ≤ m / r), not the raw one. +inf where m / r ≥ 1 (no raw opacity reaches the cap)."""
    new = filtered_log_scales(log_scales, var)
    log_q = math.log(max_opacity) - (log_scales - new).sum(dim=1)  # log(m / r)
    q = torch.exp(log_q)
    return torch.where(q < 1, log_q - torch.log1p(-q.clamp(max=1 - 1e-12)), torch.full_like(q, float("inf")))
