"""The layout loss's value and gradient in one Triton launch (the GPU side of
`gaussians.layout_loss_fn`, ~20 element-wise operations in torch): per layout row k, with
d = μ[idx_k] − u0_k, r = hypot(‖d‖, eps) and c = n̂_k·d / r (0 within the dead zone), the row's
|c| summed into the value and its gradient sign(c)/r · (n̂_k − c·d/r) added into the full-size
gradient, both in one zeroed buffer: two device operations in all. The value is summed with one
atomic addition per program, so its last bits may differ from run to run on a GPU (it is only
logged); the gradient's rows are unique (a repeated row's terms are added atomically too). eps and
the dead zone are read from a tensor in the loss's dtype: a float argument would reach a GPU's
kernel as float32 (splatting/optional_triton.py), and eps sets the gradient where μ ≈ u0."""

from __future__ import annotations

import torch

from .devices import cdiv
from .optional_triton import available as available
from .optional_triton import tl, triton

_BLOCK = 512


if triton is not None:

    @triton.jit
    def _layout(means, idx, u0, nhat, full, value, k, s_means, eps_deadzone, BLOCK: tl.constexpr):
        pid = tl.program_id(0)
        eps = tl.load(eps_deadzone)
        deadzone = tl.load(eps_deadzone + 1)
        i = pid * BLOCK + tl.arange(0, BLOCK)
        ok = i < k
        j = tl.load(idx + i, mask=ok, other=0).to(tl.int64)
        dx = tl.load(means + j * s_means, mask=ok, other=0.0) - tl.load(u0 + i * 3, mask=ok, other=0.0)
        dy = tl.load(means + j * s_means + 1, mask=ok, other=0.0) - tl.load(u0 + i * 3 + 1, mask=ok, other=0.0)
        dz = tl.load(means + j * s_means + 2, mask=ok, other=0.0) - tl.load(u0 + i * 3 + 2, mask=ok, other=0.0)
        nx = tl.load(nhat + i * 3, mask=ok, other=0.0)
        ny = tl.load(nhat + i * 3 + 1, mask=ok, other=0.0)
        nz = tl.load(nhat + i * 3 + 2, mask=ok, other=0.0)
        length2 = dx * dx + dy * dy + dz * dz
        r = tl.sqrt(length2 + eps * eps)
        ex, ey, ez = dx / r, dy / r, dz / r
        c = ex * nx + ey * ny + ez * nz
        c = tl.where(ok & (length2 > deadzone * deadzone), c, 0.0)
        tl.atomic_add(value, tl.sum(tl.abs(c), axis=0))
        w = tl.where(c > 0, 1.0, tl.where(c < 0, -1.0, 0.0)) / r  # sign(0) = 0: no gradient at μ = u0
        # atomics: a repeated row gets the sum of its terms, as with autograd
        tl.atomic_add(full + j * 3, (nx - c * ex) * w, mask=ok)
        tl.atomic_add(full + j * 3 + 1, (ny - c * ey) * w, mask=ok)
        tl.atomic_add(full + j * 3 + 2, (nz - c * ez) * w, mask=ok)


def layout_value_and_gradient(means: torch.Tensor, idx: torch.Tensor, u0: torch.Tensor, nhat_k: torch.Tensor,
                              eps_deadzone: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(L, ∂L/∂means [N,3] contiguous) for `gaussians.layout_loss_fn`: `means` [N,3] with a unit
    column stride, `idx` [K] (K ≥ 1), `u0` and `nhat_k` (the unit normals / K) [K,3] contiguous,
    `eps_deadzone` [2] (eps, the dead zone) in the means' dtype and on their device."""
    k, n = int(idx.shape[0]), int(means.shape[0])
    buffer = torch.zeros(n * 3 + 1, dtype=means.dtype, device=means.device)
    full, value = buffer[: n * 3].view(n, 3), buffer[n * 3]
    kernel, grid, args, options = layout_launch(means, idx, u0, nhat_k, full, value, k, means.stride(0),
                                                eps_deadzone)
    kernel[grid](*args, **options)
    return value, full


def layout_launch(means, idx, u0, nhat, full, value, k, s_means, eps_deadzone):
    """(kernel, grid, args, options): spelled out once, for the loss and the compile check."""
    return (_layout, (cdiv(k, _BLOCK),),
            (means, idx, u0, nhat, full, value, k, s_means, eps_deadzone),
            dict(BLOCK=_BLOCK, num_warps=4))
