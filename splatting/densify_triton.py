"""One rendered view's densification statistics in one Triton launch (the GPU side of
`gaussians.densify.DensifyStats.add`, ~14 element-wise operations in torch): per Gaussian, the norm of
its screen-space gradient (non-finite → 0) summed where it was visible, the visible count and
the largest screen radius, updated in place."""

from __future__ import annotations

import torch

from .devices import cdiv
from .optional_triton import available as available
from .optional_triton import launch_float, tl, triton

_BLOCK = 1024


if triton is not None:

    @triton.jit
    def _add(grad2d, visible, radii, grad_accum, count, max_radius, n, s_grad, s_vis, s_rad, scale, pixel_scale,
             BLOCK: tl.constexpr, FLOAT32: tl.constexpr):
        i = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
        ok = i < n
        gx = tl.load(grad2d + i * s_grad, mask=ok, other=0.0).to(grad_accum.dtype.element_ty)
        gy = tl.load(grad2d + i * s_grad + 1, mask=ok, other=0.0).to(grad_accum.dtype.element_ty)
        g = tl.sqrt(gx * gx + gy * gy) * scale
        g = tl.where((g == g) & (g < float("inf")), g, 0.0)  # nan_to_num(nan=0, posinf=0)
        r = tl.load(radii + i * s_rad, mask=ok, other=0)
        vis = (tl.load(visible + i * s_vis, mask=ok, other=0) != 0) & (r > 0)
        acc = tl.load(grad_accum + i, mask=ok, other=0.0)
        tl.store(grad_accum + i, acc + tl.where(vis, g, 0.0), mask=ok)
        c = tl.load(count + i, mask=ok, other=0.0)
        tl.store(count + i, c + vis.to(c.dtype), mask=ok)
        mr = tl.load(max_radius + i, mask=ok, other=0.0)
        if FLOAT32:  # torch's rounding: a float32 `/` is approximate on a GPU (float64's is exact)
            rr = tl.math.div_rn(r.to(mr.dtype), pixel_scale + tl.zeros_like(mr))
        else:
            rr = r.to(mr.dtype) / pixel_scale
        tl.store(max_radius + i, tl.where(vis, tl.maximum(mr, rr), mr), mask=ok)


def add_(grad2d: torch.Tensor, visible: torch.Tensor, radii: torch.Tensor, grad_accum: torch.Tensor,
         count: torch.Tensor, max_radius: torch.Tensor, scale: float, pixel_scale: float) -> None:
    """In place: `DensifyStats.add`'s update of (grad_accum, count, max_radius), all [N] contiguous;
    `grad2d` [N,2] with a unit column stride, `visible` [N] bool, `radii` [N] integer pixels."""
    n = grad_accum.shape[0]
    if n == 0:
        return
    if grad2d.stride(1) != 1:
        grad2d = grad2d.contiguous()
    vis = visible.view(torch.uint8) if visible.dtype == torch.bool else visible
    kernel, grid, args, options = add_launch(grad2d, vis, radii, grad_accum, count, max_radius, n, grad2d.stride(0),
                                             vis.stride(0), radii.stride(0), scale, pixel_scale)
    kernel[grid](*args, **options)


def add_launch(grad2d, visible, radii, grad_accum, count, max_radius, n, s_grad, s_vis, s_rad, scale, pixel_scale):
    """(kernel, grid, args, options): spelled out once, for `add_` and the compile check."""
    return (_add, (cdiv(n, _BLOCK),),
            (grad2d, visible, radii, grad_accum, count, max_radius, n, s_grad, s_vis, s_rad, launch_float(scale),
             launch_float(pixel_scale)),
            dict(BLOCK=_BLOCK, num_warps=4, FLOAT32=max_radius.dtype == torch.float32))
