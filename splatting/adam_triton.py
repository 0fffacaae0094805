"""Adam over every parameter tensor of the Gaussians in one Triton launch (the GPU side of
`gaussians.optim.Adam.step`; torch's fused Adam takes one launch per tensor, because each has its
own learning rate, and the finite check and the zeroing of non-finite gradients take one more
operation per tensor on a GPU).

The launch's programs are split over the tensors: tensor s takes ⌈numel_s / BLOCK⌉ consecutive
programs. Per element, as torch's fused Adam: a gradient value that is not finite is taken as 0
(and a flag set, by one atomic per program that met one), m ← β₁m + (1−β₁)g, v ← β₂v + (1−β₂)g²,
p ← p − (lr/(1−β₁ᵗ))·m / (√v/√(1−β₂ᵗ) + ε). The scalars reach the kernel as float32 (Triton's
type for a Python float), so a float64 parameter's update carries float32's relative rounding
(~1e-7 of a step), which training never sees."""

from __future__ import annotations

import math

import torch

from .devices import cdiv

try:
    import triton
    import triton.language as tl
except ImportError:
    triton = None

#: the most tensors one launch takes (the Gaussians' PARAM_NAMES)
SLOTS = 6
_BLOCK = 1024


def available() -> bool:
    return triton is not None


if triton is not None:

    @triton.jit
    def _update(p, g, m, v, n, step_size, block, found, beta1, one_minus_beta1, beta2, one_minus_beta2, eps,
                inv_sqrt_bc2, BLOCK: tl.constexpr):
        i = block.to(tl.int64) * BLOCK + tl.arange(0, BLOCK)
        ok = i < n
        grad = tl.load(g + i, mask=ok, other=0.0)
        finite = (grad == grad) & (tl.abs(grad) < float("inf"))
        if tl.max(tl.where(ok & ~finite, 1, 0), axis=0) > 0:
            tl.atomic_max(found, 1.0)
        grad = tl.where(finite, grad, 0.0)
        mm = beta1 * tl.load(m + i, mask=ok, other=0.0) + one_minus_beta1 * grad
        vv = beta2 * tl.load(v + i, mask=ok, other=0.0) + one_minus_beta2 * grad * grad
        tl.store(m + i, mm, mask=ok)
        tl.store(v + i, vv, mask=ok)
        denom = tl.sqrt(vv) * inv_sqrt_bc2 + eps
        tl.store(p + i, tl.load(p + i, mask=ok, other=0.0) - step_size * mm / denom, mask=ok)

    @triton.jit
    def _adam(p0, g0, m0, v0, n0, s0, e0, p1, g1, m1, v1, n1, s1, e1, p2, g2, m2, v2, n2, s2, e2,
              p3, g3, m3, v3, n3, s3, e3, p4, g4, m4, v4, n4, s4, e4, p5, g5, m5, v5, n5, s5,
              found, beta1, one_minus_beta1, beta2, one_minus_beta2, eps, inv_sqrt_bc2, BLOCK: tl.constexpr):
        # e_s: the first program past tensor s (so tensor s takes programs e_{s-1} .. e_s - 1)
        pid = tl.program_id(0)
        if pid < e0:
            _update(p0, g0, m0, v0, n0, s0, pid, found, beta1, one_minus_beta1, beta2, one_minus_beta2, eps,
                    inv_sqrt_bc2, BLOCK)
        elif pid < e1:
            _update(p1, g1, m1, v1, n1, s1, pid - e0, found, beta1, one_minus_beta1, beta2, one_minus_beta2, eps,
                    inv_sqrt_bc2, BLOCK)
        elif pid < e2:
            _update(p2, g2, m2, v2, n2, s2, pid - e1, found, beta1, one_minus_beta1, beta2, one_minus_beta2, eps,
                    inv_sqrt_bc2, BLOCK)
        elif pid < e3:
            _update(p3, g3, m3, v3, n3, s3, pid - e2, found, beta1, one_minus_beta1, beta2, one_minus_beta2, eps,
                    inv_sqrt_bc2, BLOCK)
        elif pid < e4:
            _update(p4, g4, m4, v4, n4, s4, pid - e3, found, beta1, one_minus_beta1, beta2, one_minus_beta2, eps,
                    inv_sqrt_bc2, BLOCK)
        else:
            _update(p5, g5, m5, v5, n5, s5, pid - e4, found, beta1, one_minus_beta1, beta2, one_minus_beta2, eps,
                    inv_sqrt_bc2, BLOCK)


def step_(tensors: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, float]], step: int,
          betas: tuple[float, float], eps: float, found: torch.Tensor) -> None:
    """One Adam update, in place, of each (parameter, gradient, exp_avg, exp_avg_sq, lr) in
    `tensors` (1 to SLOTS of them, each of the four contiguous, of one dtype and device; `step` is
    this update's t ≥ 1); `found` (0-dim float32 on that device) is set to 1.0 when some gradient
    value was not finite (taken as 0), and left as it is otherwise."""
    kernel, grid, args, options = adam_launch(tensors, step, betas, eps, found)
    if grid[0]:
        kernel[grid](*args, **options)


def adam_launch(tensors, step, betas, eps, found):
    """(kernel, grid, args, options): spelled out once, for the optimiser and the compile check.
    Unused slots repeat the last tensor with no programs."""
    if not 1 <= len(tensors) <= SLOTS:
        raise ValueError(f"one launch takes 1 to {SLOTS} tensors, not {len(tensors)}")
    b1, b2 = betas
    bc1, bc2 = 1.0 - b1**step, 1.0 - b2**step
    args, end = [], 0
    slots = list(tensors) + [tensors[-1][:4] + (0.0,)] * (SLOTS - len(tensors))
    for s, (p, g, m, v, lr) in enumerate(slots):
        n = _numel(p) if s < len(tensors) else 0
        end += cdiv(n, _BLOCK)
        args += [p, g, m, v, n, float(lr) / bc1]
        if s < SLOTS - 1:
            args.append(end)
    args += [found, float(b1), 1.0 - float(b1), float(b2), 1.0 - float(b2), float(eps), 1.0 / math.sqrt(bc2)]
    return _adam, (end,), tuple(args), dict(BLOCK=_BLOCK, num_warps=4)


def _numel(t) -> int:
    return t.numel() if isinstance(t, torch.Tensor) else math.prod(t.shape)
