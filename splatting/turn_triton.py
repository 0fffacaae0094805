"""A randomly turned training panorama in one Triton launch (the GPU side of
`gaussians.view_jitter`; here beside the other kernels, since this package imports nothing of
the trainer's): for each pixel of the turned copy, the direction R d of its centre,
its pixel coordinates in the original and the bicubic (or bilinear) sample there, periodic
across the ±180° seam and clamped at the poles, as `TurnMaps.maps` + `turn_panorama` compute
it with ~20 torch operations (atan2, asin, the grid and grid_sample's sampling, the clamp).

The sampling is grid_sample's with ``align_corners=True`` and border padding on the
column-wrapped image, tap for tap: cubic convolution with a = −0.75, each tap's row clamped
to [0, H − 1]; columns wrap modulo W.
"""

from __future__ import annotations

import math

import torch

from .devices import cdiv
from .optional_triton import available as available
from .optional_triton import tl, triton

if triton is not None:
    # the projection's polynomial atan2 (|error| <= 1e-8 rad: 3e-6 pixel at W = 2048); libdevice's
    # does not run in the interpreter, which CI checks this kernel with
    from .project_triton import _atan2

_BLOCK = 256


if triton is not None:

    @triton.jit
    def _cubic_near(t):  # |t| <= 1 (a = -0.75)
        return ((-0.75 + 2.0) * t - (-0.75 + 3.0)) * t * t + 1.0

    @triton.jit
    def _cubic_far(t):  # 1 < |t| < 2
        return ((-0.75 * t - 5.0 * -0.75) * t + 8.0 * -0.75) * t - 4.0 * -0.75

    @triton.jit
    def _cubic_weight(t, K: tl.constexpr):
        """The weight of tap K (0..3, at offsets −1..2 from the floor) for the fraction t."""
        if K == 0:
            w = _cubic_far(t + 1.0)
        elif K == 1:
            w = _cubic_near(t)
        elif K == 2:
            w = _cubic_near(1.0 - t)
        else:
            w = _cubic_far(2.0 - t)
        return w

    @triton.jit
    def _turn(image, dirs, rot, out, H, W, C: tl.constexpr, BICUBIC: tl.constexpr, CLAMP01: tl.constexpr,
              BLOCK: tl.constexpr):
        i = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
        inside = i < H * W
        n = H * W
        dx = tl.load(dirs + i, mask=inside, other=0.0)
        dy = tl.load(dirs + n + i, mask=inside, other=0.0)
        dz = tl.load(dirs + 2 * n + i, mask=inside, other=1.0)
        # Rᵀ d: row k of Rᵀ is column k of R (rot is row-major [3,3], float32 as TurnMaps.maps)
        x = tl.load(rot + 0) * dx + tl.load(rot + 3) * dy + tl.load(rot + 6) * dz
        y = tl.load(rot + 1) * dx + tl.load(rot + 4) * dy + tl.load(rot + 7) * dz
        z = tl.load(rot + 2) * dx + tl.load(rot + 5) * dy + tl.load(rot + 8) * dz
        two_pi = 2.0 * math.pi
        col = _atan2(x, z) * (W / two_pi) + (W / 2.0 - 0.5)
        yc = tl.minimum(tl.maximum(y, -1.0), 1.0)
        row = _atan2(yc, tl.sqrt(tl.maximum(1.0 - yc * yc, 0.0))) * (H / math.pi) + (H / 2.0 - 0.5)
        row = tl.minimum(tl.maximum(row, 0.0), H - 1.0)
        c0 = tl.floor(col)
        r0 = tl.floor(row)
        tx = col - c0
        ty = row - r0
        c0i = c0.to(tl.int32)
        r0i = r0.to(tl.int32)
        for ch in tl.static_range(C):
            acc = tl.zeros([BLOCK], dtype=tl.float32)
            if BICUBIC:
                for a in tl.static_range(4):
                    rr = tl.minimum(tl.maximum(r0i + (a - 1), 0), H - 1)
                    line = tl.zeros([BLOCK], dtype=tl.float32)
                    for b in tl.static_range(4):
                        cc = (c0i + (b - 1) + 2 * W) % W
                        v = tl.load(image + (rr * W + cc) * C + ch, mask=inside, other=0.0).to(tl.float32)
                        line += _cubic_weight(tx, b) * v
                    acc += _cubic_weight(ty, a) * line
            else:
                r1 = tl.minimum(r0i + 1, H - 1)
                ca = (c0i + 2 * W) % W
                cb = (c0i + 1 + 2 * W) % W
                v00 = tl.load(image + (r0i * W + ca) * C + ch, mask=inside, other=0.0).to(tl.float32)
                v01 = tl.load(image + (r0i * W + cb) * C + ch, mask=inside, other=0.0).to(tl.float32)
                v10 = tl.load(image + (r1 * W + ca) * C + ch, mask=inside, other=0.0).to(tl.float32)
                v11 = tl.load(image + (r1 * W + cb) * C + ch, mask=inside, other=0.0).to(tl.float32)
                acc = (v00 * (1.0 - tx) + v01 * tx) * (1.0 - ty) + (v10 * (1.0 - tx) + v11 * tx) * ty
            if CLAMP01:
                acc = tl.minimum(tl.maximum(acc, 0.0), 1.0)
            tl.store(out + i * C + ch, acc.to(out.dtype.element_ty), mask=inside)


def turn_launch(image, dirs, rot, out, h, w, channels, bicubic, clamp01):
    """(kernel, grid, args, options): spelled out once, for the trainer and the compile check."""
    grid = (cdiv(h * w, _BLOCK),)
    return _turn, grid, (image, dirs, rot, out, h, w), dict(C=channels, BICUBIC=bicubic, CLAMP01=clamp01,
                                                             BLOCK=_BLOCK, num_warps=4)


def turn(image: torch.Tensor, dirs: torch.Tensor, rotation: torch.Tensor, mode: str, clamp01: bool) -> torch.Tensor:
    """[H,W,C] float32 `image` turned by `rotation` ([3,3]; `dirs` TurnMaps.dirs, [3,H·W] float32
    on the image's device), sampled `mode` ("bicubic" or "bilinear"), clamped to [0, 1] if asked."""
    h, w = image.shape[:2]
    channels = image.shape[2]
    image = image.contiguous()
    rot = rotation.to(device=image.device, dtype=torch.float32, non_blocking=True).contiguous()
    out = torch.empty_like(image)
    kernel, grid, args, options = turn_launch(image, dirs, rot, out, h, w, channels, mode == "bicubic", clamp01)
    kernel[grid](*args, **options)
    return out
