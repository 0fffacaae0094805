"""The training loss λ1·L1 + λ2·(1 − SSIM) of a render against its image, fused into Triton kernels:
the GPU counterpart of the compiled CPU kernel's SSIM (csrc, ``ssim_forward``/``ssim_backward``).

On a GPU the torch formulation of this loss was ~90 device operations a training step (the five
blurred moments, the SSIM map, the L1 map and their backward, each an image-sized pass and a
launch). Here it is three launches forward and two backward:

* forward 1: the horizontal pass of the 11-tap Gaussian window over the five moments SSIM needs
  (μ₁, μ₂, E[x²], E[y²], E[xy] per channel; masked pixels zeroed in both images first);
* forward 2: the vertical pass, the SSIM map, and what the backward needs of it: the three maps
  ∂S/∂μ₁, ∂S/∂E[x²], ∂S/∂E[xy] (times the pixel's weight), and per-program partial sums of the
  weighted SSIM map, the weighted L1 map and the weights;
* forward 3: one program sums the partials in a fixed order (deterministic) and writes the loss,
  L1 and SSIM with the normalisers of :func:`gaussians.losses.photometric_loss`, and the PSNR of
  :func:`gaussians.losses.psnr_tensor` (the training log's, from sums the pass above makes anyway);
* backward 1 and 2: the blur of the three ∂S maps (the window is its own adjoint: symmetric, zero
  padding), combined with the L1 term's sign into the image's gradient, read and written in the
  render's [H,W,3] layout (no permute or copy).

The math is :class:`gaussians.losses._SSIM`'s, term for term; the tests compare the two.
"""

from __future__ import annotations

import math

import torch

from .devices import cdiv
from .optional_triton import available as available
from .optional_triton import tl, triton

C1, C2 = 0.01**2, 0.03**2
WINDOW, SIGMA = 11, 1.5
_BLOCK_Y, _BLOCK_X = 4, 64  # a program's tile: 2 pixels a thread, no spills (bench kernels)
_FINAL_BLOCK = 512  # six partial sums a program: 4 each a thread keeps the reduction within 64 registers
#: per-program partial sums of _ssim_v (Σ u·S, Σ u·|p − g|, Σ u, Σ m·e², Σ m, Σ e²) and _finalize's
#: outputs (loss, L1, SSIM, n_L1, n_SSIM, PSNR)
_NUM_PARTIALS = _NUM_TOTALS = 6


if triton is not None:
    _R = tl.constexpr(WINDOW // 2)
    _C1 = tl.constexpr(C1)
    _C2 = tl.constexpr(C2)
    _NPART = tl.constexpr(_NUM_PARTIALS)
    _MINUS_10_OVER_LN10 = tl.constexpr(-10.0 / math.log(10.0))  # PSNR = −10·log10(mse)

    @triton.jit
    def _blur_v(src, y, x, H, W, win, BY: tl.constexpr, BX: tl.constexpr):
        """Σ_k win[k]·src[y+k−R, x] over one [H,W] plane (zero outside): the vertical pass."""
        acc = tl.zeros([BY, BX], dtype=src.dtype.element_ty)
        for k in tl.static_range(2 * _R + 1):
            ys = y + (k - _R)
            acc += tl.load(win + k) * tl.load(src + ys * W + x, mask=(x < W) & (ys >= 0) & (ys < H), other=0.0)
        return acc

    @triton.jit
    def _moments_h(pred, gt, mask, win, out, H, W, sp_y, sp_x, sp_c, sg_y, sg_x, sg_c,
                   HAS_MASK: tl.constexpr, BY: tl.constexpr, BX: tl.constexpr):
        """out[j*3+c, y, x] = Σ_k win[k]·q_j(y, x+k−R): the horizontal blur of q = p, g, p², g², pg."""
        y = tl.program_id(0) * BY + tl.arange(0, BY)[:, None]
        x = tl.program_id(1) * BX + tl.arange(0, BX)[None, :]
        inside = (y < H) & (x < W)
        plane = H * W
        for c in tl.static_range(3):
            mu1 = tl.zeros([BY, BX], dtype=out.dtype.element_ty)
            mu2 = tl.zeros([BY, BX], dtype=out.dtype.element_ty)
            e11 = tl.zeros([BY, BX], dtype=out.dtype.element_ty)
            e22 = tl.zeros([BY, BX], dtype=out.dtype.element_ty)
            e12 = tl.zeros([BY, BX], dtype=out.dtype.element_ty)
            for k in tl.static_range(2 * _R + 1):
                xs = x + (k - _R)
                ok = (y < H) & (xs >= 0) & (xs < W)
                wk = tl.load(win + k)
                p = tl.load(pred + y * sp_y + xs * sp_x + c * sp_c, mask=ok, other=0.0)
                g = tl.load(gt + y * sg_y + xs * sg_x + c * sg_c, mask=ok, other=0.0)
                if HAS_MASK:
                    m = tl.load(mask + y * W + xs, mask=ok, other=0.0)
                    p = p * m
                    g = g * m
                mu1 += wk * p
                mu2 += wk * g
                e11 += wk * (p * p)
                e22 += wk * (g * g)
                e12 += wk * (p * g)
            at = out + y * W + x
            tl.store(at + (0 + c) * plane, mu1, mask=inside)
            tl.store(at + (3 + c) * plane, mu2, mask=inside)
            tl.store(at + (6 + c) * plane, e11, mask=inside)
            tl.store(at + (9 + c) * plane, e22, mask=inside)
            tl.store(at + (12 + c) * plane, e12, mask=inside)

    @triton.jit
    def _ssim_v(moments, pred, gt, mask, weight, win, dmaps, partials, H, W, sp_y, sp_x, sp_c, sg_y, sg_x, sg_c,
                HAS_MASK: tl.constexpr, HAS_WEIGHT: tl.constexpr, BY: tl.constexpr, BX: tl.constexpr):
        """The vertical blur, the SSIM map S and u·∂S/∂(μ₁, E[x²], E[xy]) (u: the pixel's weight,
        1 without mask and weight); partials[program] = (Σ u·S, Σ u·|p − g|, Σ u, and for the PSNR
        Σ m·e², Σ m, Σ e² with e = clamp(p, 0, 1) − g and m the mask, 1 without)."""
        y = tl.program_id(0) * BY + tl.arange(0, BY)[:, None]
        x = tl.program_id(1) * BX + tl.arange(0, BX)[None, :]
        inside = (y < H) & (x < W)
        plane = H * W
        u = tl.where(inside, 1.0, 0.0).to(dmaps.dtype.element_ty)
        if HAS_MASK:
            u = u * tl.load(mask + y * W + x, mask=inside, other=0.0)
        m = u
        if HAS_WEIGHT:
            u = u * tl.load(weight + y * W + x, mask=inside, other=0.0)
        s_sum = tl.zeros([BY, BX], dtype=dmaps.dtype.element_ty)
        l1_sum = tl.zeros([BY, BX], dtype=dmaps.dtype.element_ty)
        se_sum = tl.zeros([BY, BX], dtype=dmaps.dtype.element_ty)  # Σ over channels of e², unmasked
        for c in tl.static_range(3):
            mu1 = _blur_v(moments + (0 + c) * plane, y, x, H, W, win, BY, BX)
            mu2 = _blur_v(moments + (3 + c) * plane, y, x, H, W, win, BY, BX)
            e11 = _blur_v(moments + (6 + c) * plane, y, x, H, W, win, BY, BX)
            e22 = _blur_v(moments + (9 + c) * plane, y, x, H, W, win, BY, BX)
            e12 = _blur_v(moments + (12 + c) * plane, y, x, H, W, win, BY, BX)
            # the terms of gaussians.losses._ssim_terms, in its order
            a1 = 2.0 * (mu1 * mu2) + _C1
            a2 = 2.0 * (e12 - mu1 * mu2) + _C2
            b1 = (mu1 * mu1 + mu2 * mu2) + _C1
            b2 = (e11 + e22) - b1 + (_C1 + _C2)
            d = b1 * b2
            s = (a1 * a2) / d
            s_b2 = s / b2
            d_mu1 = 2.0 * u * ((a2 - a1) * mu2 / d + mu1 * s_b2 - mu1 * (s / b1))
            at = dmaps + y * W + x
            tl.store(at + (0 + c) * plane, d_mu1, mask=inside)
            tl.store(at + (3 + c) * plane, -u * s_b2, mask=inside)
            tl.store(at + (6 + c) * plane, 2.0 * u * (a1 / d), mask=inside)
            s_sum += tl.where(inside, u * s, 0.0)
            p = tl.load(pred + y * sp_y + x * sp_x + c * sp_c, mask=inside, other=0.0)
            g = tl.load(gt + y * sg_y + x * sg_x + c * sg_c, mask=inside, other=0.0)
            l1_sum += u * tl.abs(p - g)
            e = tl.minimum(tl.maximum(p, 0.0), 1.0) - g
            se_sum += e * e
        at = partials + (tl.program_id(0) * tl.num_programs(1) + tl.program_id(1)) * _NPART
        tl.store(at + 0, tl.sum(tl.sum(s_sum, axis=1), axis=0))
        tl.store(at + 1, tl.sum(tl.sum(l1_sum, axis=1), axis=0))
        tl.store(at + 2, tl.sum(tl.sum(u, axis=1), axis=0))
        tl.store(at + 3, tl.sum(tl.sum(m * se_sum, axis=1), axis=0))
        tl.store(at + 4, tl.sum(tl.sum(m, axis=1), axis=0))
        tl.store(at + 5, tl.sum(tl.sum(se_sum, axis=1), axis=0))

    @triton.jit
    def _finalize(partials, n_parts, out, lambda_l1, lambda_dssim, n_pixels,
                  HAS_WEIGHT: tl.constexpr, BLOCK: tl.constexpr):
        """out = (loss, L1, SSIM, n_L1, n_SSIM, PSNR): the sums in one fixed order, then the
        normalisers of photometric_loss (a mask alone: L1 over max(3·Σm, 1) as l1_loss, SSIM over
        3·Σm), and psnr_tensor's PSNR (an all-false mask: over every pixel)."""
        s_acc = tl.zeros([BLOCK], dtype=out.dtype.element_ty)
        l1_acc = tl.zeros([BLOCK], dtype=out.dtype.element_ty)
        u_acc = tl.zeros([BLOCK], dtype=out.dtype.element_ty)
        mse_acc = tl.zeros([BLOCK], dtype=out.dtype.element_ty)
        m_acc = tl.zeros([BLOCK], dtype=out.dtype.element_ty)
        se_acc = tl.zeros([BLOCK], dtype=out.dtype.element_ty)
        for start in range(0, n_parts, BLOCK):
            i = start + tl.arange(0, BLOCK)
            ok = i < n_parts
            s_acc += tl.load(partials + i * _NPART + 0, mask=ok, other=0.0)
            l1_acc += tl.load(partials + i * _NPART + 1, mask=ok, other=0.0)
            u_acc += tl.load(partials + i * _NPART + 2, mask=ok, other=0.0)
            mse_acc += tl.load(partials + i * _NPART + 3, mask=ok, other=0.0)
            m_acc += tl.load(partials + i * _NPART + 4, mask=ok, other=0.0)
            se_acc += tl.load(partials + i * _NPART + 5, mask=ok, other=0.0)
        s_total = tl.sum(s_acc, axis=0)
        l1_total = tl.sum(l1_acc, axis=0)
        u_total = tl.sum(u_acc, axis=0)
        m_total = tl.sum(m_acc, axis=0)
        mse = tl.where(m_total > 0, tl.sum(mse_acc, axis=0) / tl.maximum(3.0 * m_total, 1.0),
                       tl.sum(se_acc, axis=0) / (3.0 * n_pixels))
        psnr = tl.log(tl.maximum(mse, 1e-12)) * _MINUS_10_OVER_LN10
        n_ssim = 3.0 * tl.maximum(u_total, 1e-12)
        if HAS_WEIGHT:
            n_l1 = n_ssim
        else:
            n_l1 = tl.maximum(3.0 * u_total, 1.0)
        l1 = l1_total / n_l1
        ssim = s_total / n_ssim
        tl.store(out + 0, lambda_l1 * l1 + lambda_dssim * (1.0 - ssim))
        tl.store(out + 1, l1)
        tl.store(out + 2, ssim)
        tl.store(out + 3, n_l1)
        tl.store(out + 4, n_ssim)
        tl.store(out + 5, psnr)

    @triton.jit
    def _dmaps_h(dmaps, win, out, H, W, BY: tl.constexpr, BX: tl.constexpr):
        """The horizontal blur of the nine ∂S maps."""
        y = tl.program_id(0) * BY + tl.arange(0, BY)[:, None]
        x = tl.program_id(1) * BX + tl.arange(0, BX)[None, :]
        inside = (y < H) & (x < W)
        plane = H * W
        for j in tl.static_range(9):
            acc = tl.zeros([BY, BX], dtype=out.dtype.element_ty)
            for k in tl.static_range(2 * _R + 1):
                xs = x + (k - _R)
                ok = (y < H) & (xs >= 0) & (xs < W)
                acc += tl.load(win + k) * tl.load(dmaps + j * plane + y * W + xs, mask=ok, other=0.0)
            tl.store(out + j * plane + y * W + x, acc, mask=inside)

    @triton.jit
    def _grad_v(blurred_h, pred, gt, mask, weight, win, totals, g_loss, g_l1, g_ssim, grad_out, H, W,
                sp_y, sp_x, sp_c, sg_y, sg_x, sg_c, so_y, so_x, so_c, lambda_l1, lambda_dssim,
                HAS_MASK: tl.constexpr, HAS_WEIGHT: tl.constexpr, HAS_G_LOSS: tl.constexpr,
                HAS_G_L1: tl.constexpr, HAS_G_SSIM: tl.constexpr, BY: tl.constexpr, BX: tl.constexpr):
        """∂/∂pred of the upstream gradients times (loss, L1, SSIM): the vertical blur of the ∂S
        maps, combined with the L1 term."""
        y = tl.program_id(0) * BY + tl.arange(0, BY)[:, None]
        x = tl.program_id(1) * BX + tl.arange(0, BX)[None, :]
        inside = (y < H) & (x < W)
        plane = H * W
        k_l1 = tl.load(totals + 0) * 0.0
        k_ssim = k_l1
        if HAS_G_LOSS:
            k_l1 += lambda_l1 * tl.load(g_loss)
            k_ssim -= lambda_dssim * tl.load(g_loss)
        if HAS_G_L1:
            k_l1 += tl.load(g_l1)
        if HAS_G_SSIM:
            k_ssim += tl.load(g_ssim)
        k_l1 = k_l1 / tl.load(totals + 3)
        k_ssim = k_ssim / tl.load(totals + 4)
        m = tl.where(inside, 1.0, 0.0).to(grad_out.dtype.element_ty)
        if HAS_MASK:
            m = tl.load(mask + y * W + x, mask=inside, other=0.0)
        u = m
        if HAS_WEIGHT:
            u = u * tl.load(weight + y * W + x, mask=inside, other=0.0)
        for c in tl.static_range(3):
            # the three planes' vertical pass in one loop over the taps (three _blur_v calls spill
            # 8 B on sm_80)
            b_mu1 = tl.zeros([BY, BX], dtype=grad_out.dtype.element_ty)
            b_e11 = tl.zeros([BY, BX], dtype=grad_out.dtype.element_ty)
            b_e12 = tl.zeros([BY, BX], dtype=grad_out.dtype.element_ty)
            for k in tl.static_range(2 * _R + 1):
                ys = y + (k - _R)
                ok = (x < W) & (ys >= 0) & (ys < H)
                wk = tl.load(win + k)
                at = blurred_h + ys * W + x + c * plane
                b_mu1 += wk * tl.load(at, mask=ok, other=0.0)
                b_e11 += wk * tl.load(at + 3 * plane, mask=ok, other=0.0)
                b_e12 += wk * tl.load(at + 6 * plane, mask=ok, other=0.0)
            p = tl.load(pred + y * sp_y + x * sp_x + c * sp_c, mask=inside, other=0.0)
            g = tl.load(gt + y * sg_y + x * sg_x + c * sg_c, mask=inside, other=0.0)
            pm = p
            gm = g
            if HAS_MASK:
                pm = p * m
                gm = g * m
            d_ssim = b_mu1 + 2.0 * pm * b_e11 + gm * b_e12
            if HAS_MASK:
                d_ssim = d_ssim * m
            diff = p - g
            sign = tl.where(diff > 0, 1.0, tl.where(diff < 0, -1.0, 0.0))
            tl.store(grad_out + y * so_y + x * so_x + c * so_c, k_ssim * d_ssim + k_l1 * sign * u, mask=inside)


_WINDOWS: dict[tuple, torch.Tensor] = {}


def _window(dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    key = (dtype, str(device))
    w = _WINDOWS.get(key)
    if w is None:
        x = torch.arange(WINDOW, dtype=torch.float64) - WINDOW // 2
        g = torch.exp(-(x * x) / (2 * SIGMA * SIGMA))
        w = _WINDOWS[key] = (g / g.sum()).to(dtype=dtype, device=device)
    return w


def _strides(t: torch.Tensor) -> tuple[int, int, int]:
    return t.stride(0), t.stride(1), t.stride(2)


def _launches(pred, gt, mask, weight, win, moments, dmaps, partials, totals, lambdas, h, w, sp, sg):
    """The forward's three launches as (kernel, grid, args, options): spelled out once, for the
    loss and for the compile check (splatting/kernel_report.py)."""
    grid = (cdiv(h, _BLOCK_Y), cdiv(w, _BLOCK_X))
    has_mask, has_weight = mask is not None, weight is not None
    m = mask if has_mask else win  # any pointer: never read without the flag
    wt = weight if has_weight else win
    tile = dict(BY=_BLOCK_Y, BX=_BLOCK_X, num_warps=4)
    return [
        (_moments_h, grid, (pred, gt, m, win, moments, h, w, *sp, *sg), dict(HAS_MASK=has_mask, **tile)),
        (_ssim_v, grid, (moments, pred, gt, m, wt, win, dmaps, partials, h, w, *sp, *sg),
         dict(HAS_MASK=has_mask, HAS_WEIGHT=has_weight, **tile)),
        (_finalize, (1,), (partials, grid[0] * grid[1], totals, *lambdas, h * w),
         dict(HAS_WEIGHT=has_weight, BLOCK=_FINAL_BLOCK, num_warps=4)),
    ]


def _backward_launches(dmaps, blurred, pred, gt, mask, weight, win, totals, ups, grad, lambdas, h, w, sp, sg, so):
    """The backward's two launches, as :func:`_launches`; `ups` the upstream gradients of
    (loss, L1, SSIM), None where that output is unused."""
    grid = (cdiv(h, _BLOCK_Y), cdiv(w, _BLOCK_X))
    has_mask, has_weight = mask is not None, weight is not None
    tile = dict(BY=_BLOCK_Y, BX=_BLOCK_X, num_warps=4)
    flags = dict(HAS_G_LOSS=ups[0] is not None, HAS_G_L1=ups[1] is not None, HAS_G_SSIM=ups[2] is not None)
    ups = [win if t is None else t for t in ups]  # None: never read
    return [
        (_dmaps_h, grid, (dmaps, win, blurred, h, w), tile),
        (_grad_v, grid, (blurred, pred, gt, mask if has_mask else win, weight if has_weight else win, win, totals,
                         *ups, grad, h, w, *sp, *sg, *so, *lambdas),
         dict(HAS_MASK=has_mask, HAS_WEIGHT=has_weight, **flags, **tile)),
    ]


def _run(launches) -> None:
    for kernel, grid, args, options in launches:
        kernel[grid](*args, **options)


class _FusedPhotometric(torch.autograd.Function):
    @staticmethod
    def forward(ctx, pred, gt, mask, weight, lambda_l1: float, lambda_dssim: float):
        h, w = pred.shape[:2]
        dev, dt = pred.device, pred.dtype
        win = _window(dt, dev)
        tiles = cdiv(h, _BLOCK_Y) * cdiv(w, _BLOCK_X)
        moments = torch.empty((15, h, w), dtype=dt, device=dev)
        dmaps = torch.empty((9, h, w), dtype=dt, device=dev)
        partials = torch.empty((tiles, _NUM_PARTIALS), dtype=dt, device=dev)
        totals = torch.empty(_NUM_TOTALS, dtype=dt, device=dev)
        lambdas = (float(lambda_l1), float(lambda_dssim))
        _run(_launches(pred, gt, mask, weight, win, moments, dmaps, partials, totals, lambdas, h, w,
                       _strides(pred), _strides(gt)))
        ctx.save_for_backward(pred, gt, mask, weight, dmaps, totals)
        ctx.lambdas = lambdas
        ctx.set_materialize_grads(False)
        psnr = totals[5]
        ctx.mark_non_differentiable(psnr)
        return totals[0], totals[1], totals[2], psnr

    @staticmethod
    def backward(ctx, g_loss, g_l1, g_ssim, _g_psnr):
        pred, gt, mask, weight, dmaps, totals = ctx.saved_tensors
        if g_loss is None and g_l1 is None and g_ssim is None:
            return None, None, None, None, None, None
        h, w = pred.shape[:2]
        win = _window(pred.dtype, pred.device)
        blurred = torch.empty_like(dmaps)
        grad = torch.empty((h, w, 3), dtype=pred.dtype, device=pred.device)
        ups = [None if t is None else t.contiguous() for t in (g_loss, g_l1, g_ssim)]
        _run(_backward_launches(dmaps, blurred, pred, gt, mask, weight, win, totals, ups, grad, ctx.lambdas, h, w,
                                _strides(pred), _strides(gt), _strides(grad)))
        return grad, None, None, None, None, None


def photometric_loss(pred: torch.Tensor, gt: torch.Tensor, lambda_l1: float, lambda_dssim: float,
                     mask: torch.Tensor | None = None, weight: torch.Tensor | None = None
                     ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """(λ1·L1 + λ2·(1 − SSIM), L1, SSIM, PSNR) of [H,W,3] images as
    :func:`gaussians.losses.photometric_loss` and :func:`gaussians.losses.psnr_tensor` compute them
    (11-tap window, σ 1.5, zero padding; `mask` [H,W] bool and `weight` [H,W] as there; the PSNR
    unweighted, over the mask), differentiable in `pred` (the PSNR not at all)."""
    if not math.isfinite(lambda_l1) or not math.isfinite(lambda_dssim):
        raise ValueError("the loss weights must be finite")
    m = None if mask is None else mask.to(pred.dtype).contiguous()
    wt = None if weight is None else weight.to(pred.dtype).contiguous()
    return _FusedPhotometric.apply(pred, gt.detach(), m, wt, lambda_l1, lambda_dssim)
