"""Adam over every parameter tensor of the Gaussians in one Triton launch (the GPU side of
`gaussians.optim.Adam.step`; torch's fused Adam takes one launch per tensor, because each has its
own learning rate, and the finite check and the zeroing of non-finite gradients take one more
operation per tensor on a GPU).

The launch's programs are split over the tensors (passed as tuples, the loop over them unrolled):
tensor s takes ⌈numel_s / BLOCK⌉ consecutive programs. Per element, as torch's fused Adam: a
gradient value that is not finite is taken as 0 (and a flag set, by one atomic per program that
met one), m ← β₁m + (1−β₁)g, v ← β₂v + (1−β₂)g²,
p ← p − (lr/(1−β₁ᵗ))·m / (√v/√(1−β₂ᵗ) + ε). The scalars reach the kernel as float32 (Triton's
type for a Python float; `launch_float` rounds them so for the interpreter too), so a float64
parameter's moments carry float32's rounding of β (~2e-8 of their value) and its update ~1e-7 of
a step, which training never sees."""

from __future__ import annotations

import math

import torch

from .devices import cdiv
from .optional_triton import available as available
from .optional_triton import launch_float, tl, triton

_BLOCK = 1024


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
    def _adam(parameters, grads, exp_avgs, exp_avg_sqs, numels, step_sizes, found, beta1, one_minus_beta1, beta2,
              one_minus_beta2, eps, inv_sqrt_bc2, SLOTS: tl.constexpr, BLOCK: tl.constexpr):
        # tensor s takes the programs from `start` (the sum of the earlier tensors' ⌈numel / BLOCK⌉)
        # to `end` − 1, worked out here: passed in, these boundaries would be specialised by Triton
        # (`% 16`, `== 1`) into a new compiled variant at most densifications (13 in 40 sizes), where
        # the numels give at most 3 (N % 16). (Not an argument named `params`: Triton's launcher
        # binds the arguments into a local of that name)
        pid = tl.program_id(0)
        start = 0
        for s in tl.static_range(SLOTS):
            end = start + tl.cdiv(numels[s], BLOCK)
            if (pid >= start) & (pid < end):
                _update(parameters[s], grads[s], exp_avgs[s], exp_avg_sqs[s], numels[s], step_sizes[s], pid - start,
                        found, beta1, one_minus_beta1, beta2, one_minus_beta2, eps, inv_sqrt_bc2, BLOCK)
            start = end


def step_(tensors: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, float]], step: int,
          betas: tuple[float, float], eps: float, found: torch.Tensor) -> None:
    """One Adam update, in place, of each (parameter, gradient, exp_avg, exp_avg_sq, lr) in
    `tensors` (at least one; each of the four contiguous, of one dtype and device; `step` is
    this update's t ≥ 1); `found` (0-dim float32 on that device) is set to 1.0 when some gradient
    value was not finite (taken as 0), and left as it is otherwise."""
    kernel, grid, args, options = adam_launch(tensors, step, betas, eps, found)
    if grid[0]:
        kernel[grid](*args, **options)


def adam_launch(tensors, step, betas, eps, found):
    """(kernel, grid, args, options): spelled out once, for the optimiser and the compile check."""
    if not tensors:
        raise ValueError("one launch needs at least one tensor")
    b1, b2 = betas
    bc1, bc2 = 1.0 - b1**step, 1.0 - b2**step
    params, grads, exp_avgs, exp_avg_sqs, lrs = zip(*tensors)
    programs = sum(cdiv(_numel(p), _BLOCK) for p in params)
    args = (params, grads, exp_avgs, exp_avg_sqs, tuple(_numel(p) for p in params),
            tuple(launch_float(float(lr) / bc1) for lr in lrs), found,
            *map(launch_float, (b1, 1.0 - float(b1), b2, 1.0 - float(b2), eps, 1.0 / math.sqrt(bc2))))
    return _adam, (programs,), args, dict(SLOTS=len(tensors), BLOCK=_BLOCK, num_warps=4)


def _numel(t) -> int:
    return t.numel() if isinstance(t, torch.Tensor) else math.prod(t.shape)
