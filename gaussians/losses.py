"""Training losses: L1, D-SSIM (3DGS's 11×11 Gaussian-window SSIM), PSNR and L_layout."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

__all__ = ["l1_loss", "ssim", "psnr", "psnr_tensor", "layout_loss", "photometric_loss", "LAYOUT_EPS",
           "ssim_map", "solid_angle_weight"]

#: Displacement (metres) below which L_layout fades to 0: it regularises the
#: 0/0 at μ = u0 (value 0, zero and finite gradient there) and changes the
#: cosine by less than 1e-12 relative for any movement ≥ 1 µm.
LAYOUT_EPS = 1e-12


def l1_loss(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Mean |pred − gt| of [H,W,3] images, over the valid pixels of `mask` ([H,W] bool) if given."""
    if mask is None:
        return (pred - gt).abs().mean()
    m = mask[..., None].to(pred.dtype)
    return ((pred - gt).abs() * m).sum() / (3.0 * m.sum()).clamp_min(1.0)  # no valid pixel: 0, not 0/0


_WINDOWS: dict[tuple, torch.Tensor] = {}


def _window_1d(size: int, sigma: float, channels: int, dtype, device) -> torch.Tensor:
    key = (size, sigma, channels, dtype, str(device))
    w = _WINDOWS.get(key)
    if w is None:
        x = torch.arange(size, dtype=torch.float64) - size // 2
        g = torch.exp(-(x * x) / (2 * sigma * sigma))
        w = (g / g.sum()).expand(channels, 1, 1, size).contiguous().to(dtype=dtype, device=device)
        _WINDOWS[key] = w
    return w


def _blur(x: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """The 2D Gaussian window as two 1D passes (same result as the 11×11 kernel, 5× fewer operations)."""
    c, pad = x.shape[1], w.shape[-1] // 2
    x = F.conv2d(x, w, padding=(0, pad), groups=c)
    return F.conv2d(x, w.transpose(2, 3), padding=(pad, 0), groups=c)


def ssim(pred: torch.Tensor, gt: torch.Tensor, window: int = 11, sigma: float = 1.5,
         mask: torch.Tensor | None = None, return_map: bool = False) -> torch.Tensor:
    """Mean SSIM of two [H,W,3] (or [B,3,H,W]) images in [0,1], as the 3DGS code computes it
    (Gaussian window, zero padding). With `mask` ([H,W] bool): masked-out pixels are zeroed in
    both images (their content has no effect) and the map is averaged over valid pixels only.
    `return_map`: the [B,H,W] map (channel mean) instead of its mean."""
    if mask is not None:
        m = mask[..., None].to(pred.dtype)
        pred, gt = pred * m, gt * m
    if pred.ndim == 3:
        pred = pred.permute(2, 0, 1)[None]
        gt = gt.permute(2, 0, 1)[None]
    c = pred.shape[1]
    w = _window_1d(window, sigma, c, pred.dtype, pred.device)
    # one batched pass over the five maps SSIM needs
    maps = _blur(torch.cat([pred, gt, pred * pred, gt * gt, pred * gt], 1), w.repeat(5, 1, 1, 1))
    mu1, mu2, e11, e22, e12 = maps.split(c, dim=1)
    mu1_sq, mu2_sq, mu12 = mu1 * mu1, mu2 * mu2, mu1 * mu2
    s1, s2, s12 = e11 - mu1_sq, e22 - mu2_sq, e12 - mu12
    c1, c2 = 0.01**2, 0.03**2
    m = ((2 * mu12 + c1) * (2 * s12 + c2)) / ((mu1_sq + mu2_sq + c1) * (s1 + s2 + c2))
    if return_map:
        return m.mean(dim=1)
    if mask is not None:
        return (m.mean(dim=1)[0] * mask.to(m.dtype)).sum() / mask.sum().clamp_min(1)
    return m.mean()


def ssim_map(pred: torch.Tensor, gt: torch.Tensor, window: int = 11, sigma: float = 1.5,
             mask: torch.Tensor | None = None) -> torch.Tensor:
    """The per-pixel SSIM of two [H,W,3] images (channel mean) as [H,W] (masked pixels zeroed
    in both images first, as in :func:`ssim`)."""
    return ssim(pred, gt, window, sigma, mask, return_map=True)[0]


def psnr(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None) -> float:
    """PSNR in dB of images in [0,1] (pred clamped to [0,1]), over `mask`'s valid pixels if given."""
    return float(psnr_tensor(pred, gt, mask))


def psnr_tensor(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """:func:`psnr` as a 0-dim tensor on the images' device, computed without a host sync
    (the training loop reads it only when it logs). An all-false mask means every pixel."""
    err = (pred.detach().clamp(0, 1) - gt) ** 2
    mse = err.mean()
    if mask is not None:
        m = mask.to(err.dtype)[..., None]
        n = m.sum() * err.shape[-1]
        mse = torch.where(n > 0, (err * m).sum() / n.clamp_min(1), mse)
    return 10.0 * torch.log10(1.0 / mse.clamp_min(1e-12))


def layout_loss(means: torch.Tensor, u0: torch.Tensor, normals: torch.Tensor, mask: torch.Tensor | None = None,
                eps: float = LAYOUT_EPS) -> torch.Tensor:
    """L_layout = mean over (masked) Gaussians of |n·(μ−u0)| / (‖n‖·‖μ−u0‖).

    The cosine between a Gaussian's movement and its plane's normal. It is 0/0
    at μ = u0; `eps` (metres) enters as ‖μ−u0‖ → sqrt(‖μ−u0‖² + eps²), so that
    case gives 0 with a zero (finite) gradient, and nothing else changes
    measurably. No masked Gaussian -> 0 (still attached to the graph).
    """
    if mask is not None:
        means, u0, normals = means[mask], u0[mask], normals[mask]
    if means.shape[0] == 0:
        return means.sum() * 0.0
    d = means - u0
    num = (d * normals).sum(-1).abs()
    dn = torch.sqrt((d * d).sum(-1) + eps * eps)
    nn = torch.sqrt((normals * normals).sum(-1)).clamp_min(1e-12)
    return (num / (nn * dn)).mean()


def photometric_loss(pred: torch.Tensor, gt: torch.Tensor, lambda_l1: float = 0.8, lambda_dssim: float = 0.2,
                     mask: torch.Tensor | None = None, weight: torch.Tensor | None = None
                     ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(λ1·L1 + λ2·(1−SSIM), L1, SSIM) of [H,W,3] images, over `mask`'s valid pixels if given.
    `weight` ([H,W], >= 0) weighs the per-pixel L1 and SSIM maps (e.g. each pixel's solid angle,
    `solid_angle_weight`); the means are then weighted means over the valid pixels."""
    if weight is None:
        l1 = l1_loss(pred, gt, mask)
        s = ssim(pred, gt, mask=mask) if lambda_dssim > 0 else pred.new_tensor(1.0)
    else:
        w = weight.to(pred.dtype) if mask is None else weight.to(pred.dtype) * mask.to(pred.dtype)
        norm = w.sum().clamp_min(1e-12)
        l1 = ((pred - gt).abs().mean(-1) * w).sum() / norm
        s = (ssim_map(pred, gt, mask=mask) * w).sum() / norm if lambda_dssim > 0 else pred.new_tensor(1.0)
    return lambda_l1 * l1 + lambda_dssim * (1.0 - s), l1, s


def solid_angle_weight(height: int, width: int, dtype=torch.float32, device="cpu") -> torch.Tensor:
    """[H,W] cos(latitude) of each equirectangular pixel centre, scaled to mean 1: proportional to
    the pixel's solid angle, so a weighted mean over the panorama weighs every steradian alike
    (an unweighted one counts the rows near the poles 1/cos(latitude) times more per steradian)."""
    lat = (0.5 - (torch.arange(height, dtype=torch.float64) + 0.5) / height) * math.pi
    w = torch.cos(lat).clamp_min(0.0)
    w = (w / w.mean())[:, None].expand(height, width)
    return w.to(dtype=dtype, device=device).contiguous()
