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


_no_weight = torch.empty(0)


def _cpu_kernels(x: torch.Tensor):
    """The compiled CPU kernels (splatting's C++ extension) for a CPU float tensor, else None."""
    if x.device.type != "cpu" or x.dtype not in (torch.float32, torch.float64):
        return None
    from splatting import raster_cpp

    return raster_cpp.load()


def _blur(x: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """The 2D Gaussian window as two 1D passes (same result as the 11×11 kernel, 5× fewer operations).

    On the CPU the compiled kernel's separable blur does it (torch's depthwise conv2d takes
    ~6× as long there); elsewhere, or without the compiled kernel, conv2d."""
    mod = _cpu_kernels(x)
    if mod is not None:
        return mod.blur_separable(x.contiguous(), w[0, 0, 0])
    c, pad = x.shape[1], w.shape[-1] // 2
    x = F.conv2d(x, w, padding=(0, pad), groups=c)
    return F.conv2d(x, w.transpose(2, 3), padding=(pad, 0), groups=c)


def ssim(pred: torch.Tensor, gt: torch.Tensor, window: int = 11, sigma: float = 1.5,
         mask: torch.Tensor | None = None, weight: torch.Tensor | None = None) -> torch.Tensor:
    """Mean SSIM of two [H,W,3] (or [B,3,H,W]) images in [0,1], as the 3DGS code computes it
    (Gaussian window, zero padding). With `mask` ([H,W] bool, or [B,H,W] for a batch): masked-out
    pixels are zeroed in both images (their content has no effect) and the map is averaged over
    valid pixels only. With `weight` ([H,W] or [B,H,W], >= 0): the weighted mean of the map
    (channel mean) over the valid pixels instead. Differentiable in `pred` only (its gradient is
    written out, see _SSIM)."""
    if mask is not None:
        m = mask[..., None].to(pred.dtype) if pred.ndim == 3 else mask[:, None].to(pred.dtype)
        pred, gt = pred * m, gt * m
    if pred.ndim == 3:
        pred = pred.permute(2, 0, 1)[None]
        gt = gt.permute(2, 0, 1)[None]
    w = _window_1d(window, sigma, pred.shape[1], pred.dtype, pred.device)
    wt = None
    if weight is not None or mask is not None:  # per-pixel weights of the channel-mean map, summing to 1
        wt = torch.ones((), dtype=pred.dtype, device=pred.device) if weight is None else weight.to(pred.dtype)
        if mask is not None:
            wt = wt * mask.to(pred.dtype)
        wt = wt / wt.sum().clamp_min(1e-12)
    return _SSIM.apply(pred, gt.detach(), w, wt)


class _SSIM(torch.autograd.Function):
    """SSIM's map summed with weights (`weight` [H,W] or [B,H,W] over the channel mean, or the
    plain mean), with its gradient in closed form: the map S = A1·A2 / (B1·B2) depends on `pred`
    through the blurred μ1, E[x²], E[xy] only, so the gradient is three blurred maps (the blur is
    its own adjoint: a symmetric window with zero padding), about half the work of autograd's
    convolution backward and its elementwise chain."""

    C1, C2 = 0.01**2, 0.03**2

    @staticmethod
    def forward(ctx, pred, gt, w, weight):
        c = pred.shape[1]
        # the compiled kernel takes one [H,W] weight map; a per-image one ([B,H,W], the crop
        # loss's masks) goes the torch way
        mod = _cpu_kernels(pred) if weight is None or weight.ndim == 2 else None
        ctx.fused = mod is not None
        if ctx.fused:  # the same math in the compiled kernel: one pass each side of the blurs
            pred, gt = pred.contiguous(), gt.contiguous()
            maps, total = mod.ssim_forward(pred, gt, w[0, 0, 0], _no_weight if weight is None else weight)
            ctx.save_for_backward(pred, gt, w, weight, maps)
            ctx.scale = 1.0 / c if weight is not None else 1.0 / pred.numel()
            return (total * ctx.scale).to(pred.dtype)
        # one batched pass over the five maps SSIM needs; then in-place and fused (addcmul)
        # operations: each image-sized operation is a pass over memory
        maps = _blur(torch.cat([pred, gt, pred * pred, gt * gt, pred * gt], 1), w.repeat(5, 1, 1, 1))
        mu1, mu2, e11, e22, e12 = maps.split(c, dim=1)
        a1, a2, b1, b2, d, smap = _ssim_terms(mu1, mu2, e11, e22, e12)
        out = smap.mean() if weight is None else (smap.mean(dim=1) * weight).sum()
        ctx.save_for_backward(pred, gt, w, weight, mu1, mu2, a1, a2, b1, b2, d, smap)
        ctx.has_weight = weight is not None
        return out

    @staticmethod
    def backward(ctx, grad):
        if ctx.fused:
            pred, gt, w, weight, maps = ctx.saved_tensors
            g = _cpu_kernels(pred).ssim_backward(pred, gt, maps, w[0, 0, 0], _no_weight if weight is None else weight,
                                                 float(grad) * ctx.scale)
            return g, None, None, None
        pred, gt, w, weight, mu1, mu2, a1, a2, b1, b2, d, smap = ctx.saved_tensors
        c = pred.shape[1]
        # d(out)/d(map) per pixel ([H,W] or [B,1,H,W] against the [B,C,H,W] maps)
        if ctx.has_weight:
            k = grad * weight / c
            k = k[:, None] if k.ndim == 3 else k
        else:
            k = grad / smap.numel()
        # ∂S/∂μ1, ∂S/∂E[x²], ∂S/∂E[xy] (μ2, E[y²] are constants), scaled by k, written
        # straight into the buffer the blur reads
        maps = torch.empty((pred.shape[0], 3 * c) + tuple(pred.shape[2:]), dtype=pred.dtype, device=pred.device)
        d_mu1, d_e11, d_e12 = maps.split(c, dim=1)
        torch.div(smap, b2, out=d_e11)  # S / B2
        torch.div(a1, d, out=d_e12)  # A1 / D
        # 2 μ2 (A2 − A1) / D + 2 μ1 S (1/B2 − 1/B1)
        torch.sub(a2, a1, out=d_mu1).mul_(mu2).div_(d)
        d_mu1.addcmul_(mu1, d_e11).addcmul_(mu1, torch.div(smap, b1), value=-1).mul_(2 * k)
        d_e11.mul_(-k)
        d_e12.mul_(2 * k)
        bl = _blur(maps, w.repeat(3, 1, 1, 1))
        g_mu1, g_e11, g_e12 = bl.split(c, dim=1)
        return g_mu1.addcmul_(pred, g_e11, value=2).addcmul_(gt, g_e12), None, None, None


def _ssim_terms(mu1, mu2, e11, e22, e12):
    """(A1, A2, B1, B2, D = B1·B2, S = A1·A2 / D) of SSIM from the blurred moments."""
    c1, c2 = _SSIM.C1, _SSIM.C2
    a1 = torch.mul(mu1, mu2).mul_(2).add_(c1)  # 2 μ1μ2 + C1
    a2 = torch.addcmul(e12, mu1, mu2, value=-1).mul_(2).add_(c2)  # 2 σ12 + C2
    b1 = torch.addcmul(torch.mul(mu1, mu1), mu2, mu2).add_(c1)  # μ1² + μ2² + C1
    b2 = torch.add(e11, e22).sub_(b1).add_(c1 + c2)  # σ1² + σ2² + C2
    d = b1 * b2
    return a1, a2, b1, b2, d, torch.mul(a1, a2).div_(d)


def ssim_map(pred: torch.Tensor, gt: torch.Tensor, window: int = 11, sigma: float = 1.5,
             mask: torch.Tensor | None = None) -> torch.Tensor:
    """The per-pixel SSIM of two [H,W,3] images (channel mean) as [H,W] (masked pixels zeroed in
    both images first, as in :func:`ssim`); not differentiable (a diagnostic: losses use `ssim`'s
    `weight`)."""
    with torch.no_grad():
        if mask is not None:
            m = mask[..., None].to(pred.dtype)
            pred, gt = pred * m, gt * m
        p, g = pred.permute(2, 0, 1)[None], gt.permute(2, 0, 1)[None]
        w = _window_1d(window, sigma, 3, pred.dtype, pred.device)
        maps = _blur(torch.cat([p, g, p * p, g * g, p * g], 1), w.repeat(5, 1, 1, 1))
        return _ssim_terms(*maps.split(3, dim=1))[-1].mean(dim=1)[0]


def psnr(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None) -> float:
    """PSNR in dB of images in [0,1] (pred clamped to [0,1]), over `mask`'s valid pixels if given."""
    return float(psnr_tensor(pred, gt, mask))


def psnr_tensor(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """:func:`psnr` as a 0-dim tensor on the images' device, computed without a host sync
    (the training loop reads it only when it logs). An all-false mask means every pixel."""
    clamped = pred.detach().clamp(0, 1)
    if mask is None:  # the training loop's PSNR every step: few operations (issue 35)
        return torch.log10(F.mse_loss(clamped, gt).clamp_min_(1e-12)).mul_(-10.0)
    err = (clamped - gt) ** 2
    m = mask.to(err.dtype)[..., None]
    n = m.sum() * err.shape[-1]
    mse = torch.where(n > 0, (err * m).sum() / n.clamp_min(1), err.mean())
    return 10.0 * torch.log10(1.0 / mse.clamp_min(1e-12))


def layout_loss(means: torch.Tensor, u0: torch.Tensor, normals: torch.Tensor, mask: torch.Tensor | None = None,
                eps: float = LAYOUT_EPS, deadzone: float = 0.0) -> torch.Tensor:
    """L_layout = mean over (masked) Gaussians of |n·(μ−u0)| / (‖n‖·‖μ−u0‖).

    The cosine between a Gaussian's movement and its plane's normal. It is 0/0
    at μ = u0; `eps` (metres) enters as ‖μ−u0‖ → sqrt(‖μ−u0‖² + eps²), so that
    case gives 0 with a zero (finite) gradient, and nothing else changes
    measurably. A Gaussian within `deadzone` of its anchor (‖μ−u0‖ ≤ deadzone)
    contributes 0 (still counted in the mean). No masked Gaussian -> 0 (still
    attached to the graph).
    """
    if mask is not None:
        means, u0, normals = means[mask], u0[mask], normals[mask]
    if means.shape[0] == 0:
        return means.sum() * 0.0
    d = means - u0
    num = (d * normals).sum(-1).abs()
    dn = torch.sqrt((d * d).sum(-1) + eps * eps)
    nn = torch.sqrt((normals * normals).sum(-1)).clamp_min(1e-12)
    cos = num / (nn * dn)
    if deadzone > 0:
        cos = torch.where((d * d).sum(-1) > deadzone * deadzone, cos, torch.zeros_like(cos))
    return cos.mean()


def photometric_loss(pred: torch.Tensor, gt: torch.Tensor, lambda_l1: float = 0.8, lambda_dssim: float = 0.2,
                     mask: torch.Tensor | None = None, weight: torch.Tensor | None = None, with_psnr: bool = False
                     ) -> tuple[torch.Tensor, ...]:
    """(λ1·L1 + λ2·(1−SSIM), L1, SSIM) of [H,W,3] images, over `mask`'s valid pixels if given.
    `weight` ([H,W], >= 0) weighs the per-pixel L1 and SSIM maps (e.g. each pixel's solid angle,
    `solid_angle_weight`); the means are then weighted means over the valid pixels. With
    `with_psnr`, a fourth value: :func:`psnr_tensor` of the same images and mask (unweighted).

    On a GPU (or where ``splatting.devices.KERNELS_ON_CPU`` is set: the interpreter, in tests)
    the same loss runs as five fused kernels (splatting/photometric_triton.py) instead of ~90
    operations; they give the PSNR too, from sums they make anyway."""
    if _fused(pred, gt, lambda_dssim):
        from splatting import photometric_triton

        terms = photometric_triton.photometric_loss(pred, gt, lambda_l1, lambda_dssim, mask=mask, weight=weight)
        return terms if with_psnr else terms[:3]
    terms = _photometric_loss(pred, gt, lambda_l1, lambda_dssim, mask, weight)
    return (*terms, psnr_tensor(pred, gt, mask)) if with_psnr else terms


def _photometric_loss(pred, gt, lambda_l1, lambda_dssim, mask, weight):
    if weight is None:
        l1 = l1_loss(pred, gt, mask)
        s = ssim(pred, gt, mask=mask) if lambda_dssim > 0 else pred.new_tensor(1.0)
    else:
        w = weight.to(pred.dtype) if mask is None else weight.to(pred.dtype) * mask.to(pred.dtype)
        l1 = ((pred - gt).abs().mean(-1) * w).sum() / w.sum().clamp_min(1e-12)
        s = ssim(pred, gt, mask=mask, weight=weight) if lambda_dssim > 0 else pred.new_tensor(1.0)
    return lambda_l1 * l1 + lambda_dssim * (1.0 - s), l1, s


def _fused(pred: torch.Tensor, gt: torch.Tensor, lambda_dssim: float) -> bool:
    """Whether photometric_loss takes the fused kernels: [H,W,3] float images where the training
    kernels run (splatting.devices.takes_kernels), SSIM on (without it, L1 alone is a few
    operations anyway)."""
    if lambda_dssim <= 0 or pred.ndim != 3 or pred.shape[-1] != 3 or gt.shape != pred.shape:
        return False
    if pred.dtype not in (torch.float32, torch.float64) or gt.dtype != pred.dtype:
        return False
    from splatting.devices import takes_kernels

    return takes_kernels(pred)


def solid_angle_weight(height: int, width: int, dtype=torch.float32, device="cpu") -> torch.Tensor:
    """[H,W] cos(latitude) of each equirectangular pixel centre, scaled to mean 1: proportional to
    the pixel's solid angle, so a weighted mean over the panorama weighs every steradian alike
    (an unweighted one counts the rows near the poles 1/cos(latitude) times more per steradian)."""
    lat = (0.5 - (torch.arange(height, dtype=torch.float64) + 0.5) / height) * math.pi
    w = torch.cos(lat).clamp_min(0.0)
    w = (w / w.mean())[:, None].expand(height, width)
    return w.to(dtype=dtype, device=device).contiguous()
