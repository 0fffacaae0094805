"""The ``cuda`` backend's tile rasteriser: Triton kernels, forward and backward.

Projection (splatting/project_triton.py) and binning (splatting/bin_triton.py) produce the
packed rows and per-tile lists; these two kernels replace
:class:`splatting.raster_torch.TorchRaster` and implement exactly its math (and the ``cpp``
kernel's). They have the form of the CUDA rasterisers (3DGS, gsplat): the tile's pixels are the
lanes, and the tile's list is walked one Gaussian at a time, its parameters read with scalar
(broadcast) loads, so nothing of size Gaussians × pixels is ever held in registers. The
reasons and the compiled numbers are in docs/gpu.md.

* Forward: front to back; per pixel T, the colour/depth sums and the index of the last
  Gaussian blended. The Gaussian is one ``exp2`` (the conic and the cutoff are scaled by
  −log2 e once per Gaussian) and 1/c one ``rsqrt(c²)`` (c > 0 wherever a pixel is kept),
  so no range fix-ups; the program checks "is any pixel of the tile unsaturated" once per
  ``BATCH`` Gaussians and stops when none is.
* Backward (as gsplat): back to front from the tile's last blend; each pixel's
  transmittance is recovered by dividing by (1 − α); a Gaussian that hits no pixel of the
  program is skipped (a uniform branch). Its 19 gradients are summed over the program's
  pixels inside one warp (shuffles, no barrier), gathered into one vector (lane j holds
  parameter j) and added with one relaxed atomic per lane.
* Indices are int32 (up to 2³¹ pairs); each program is one warp; float64 splits a tile
  over two programs so that it needs no spills (``LAUNCH``).

Memory: O(Gaussians + pairs + pixels), nothing of size pixels × Gaussians.

Triton reads ``TRITON_INTERPRET`` when ``@triton.jit`` decorates a function, and its
own library functions (``tl.sum``, ``tl.cumprod``) are decorated when ``triton`` is first
imported: the interpreter is therefore a process-wide choice, made before ``triton`` is
imported (the test suite's conftest sets it on machines without CUDA). With it, the
same kernels run on CPU tensors, which is how CI checks them.
"""

from __future__ import annotations

import torch

from .project import ALPHA_MAX, C_MIN, PACK, T_MIN

try:
    import triton
    import triton.language as tl

    _IMPORT_ERROR = None
except ImportError as exc:  # the backend reports it; the rest of the package works without triton
    triton = None
    _IMPORT_ERROR = exc

BATCH = 32  # forward: Gaussians walked between two "is any pixel of the tile still unsaturated" votes
# (warps per program, programs per tile) by kernel and element size. One warp per program: the
# backward's per-Gaussian sums over pixels are shuffles, never a barrier. float32: one program per
# 16x16 tile (8 pixels per thread, so the 20 broadcast loads of a Gaussian are shared by 8 pairs);
# float64 values take two registers each, so a tile is split over two programs (4 pixels per thread)
# to stay free of spills. docs/gpu.md has the comparison of the alternatives.
LAUNCH = {("forward", 4): (1, 1), ("forward", 8): (1, 2), ("backward", 4): (1, 1), ("backward", 8): (1, 2)}
SPLIT_IN_INTERPRETER = False  # a test sets it to run the split launches in the interpreter too

if triton is not None:
    _ALPHA_MAX = tl.constexpr(ALPHA_MAX)
    _C_MIN = tl.constexpr(C_MIN)
    _T_MIN = tl.constexpr(T_MIN)
    _PACK = tl.constexpr(PACK)
    _NLOG2E = tl.constexpr(-1.4426950408889634)  # −log2(e): exp(−x) = exp2(−x·log2 e)
    _NHALF_LOG2E = tl.constexpr(-0.7213475204444817)

    # Reductions over the pixel axis, spelled as the `tl.reduce` that `tl.sum` / `tl.max` wrap:
    # compiled, the same code; interpreted, no per-call re-patching of triton.language (each
    # jit-function call costs the interpreter ~1 ms, 20 of them per Gaussian in the backward).
    from triton.language.standard import _elementwise_max, _sum_combine

    @triton.jit
    def _tile_pixels(pid, H, W, TS, SPLIT: tl.constexpr, BLOCK_PIX: tl.constexpr):
        """The tile of program ``pid`` (SPLIT programs share a tile, each a slice of its pixels):
        the tile, the flat pixel index of each slot and whether it is inside the image (int32)."""
        tile = pid // SPLIT
        ntx = (W + TS - 1) // TS
        i = (pid % SPLIT) * BLOCK_PIX + tl.arange(0, BLOCK_PIX)
        row = (tile // ntx) * TS + i // TS
        col = (tile % ntx) * TS + i % TS
        ok = (i < TS * TS) & (row < H) & (col < W)
        return tile, row * W + col, ok

    @triton.jit
    def _raster_fwd(P, dirs, toff, tlist, bg, out_color, out_depth, out_T, out_last, npx, H, W, TS,
                    BATCH: tl.constexpr, SPLIT: tl.constexpr, BLOCK_PIX: tl.constexpr, HAS_BG: tl.constexpr):
        tile, pix, pok = _tile_pixels(tl.program_id(0), H, W, TS, SPLIT, BLOCK_PIX)
        # pixels outside the image get d = 0, hence c = 0: never kept, no mask needed in the loop
        dx = tl.load(dirs + pix * 3, mask=pok, other=0)
        dy = tl.load(dirs + pix * 3 + 1, mask=pok, other=0)
        dz = tl.load(dirs + pix * 3 + 2, mask=pok, other=0)
        T = dx * 0 + 1.0  # in the working dtype (float32 or float64)
        acc_r, acc_g, acc_b, acc_d = T * 0, T * 0, T * 0, T * 0
        last = tl.full((BLOCK_PIX,), -1, tl.int32)
        k0 = tl.load(toff + tile)
        end = tl.load(toff + tile + 1)
        live = 1
        # batches of Gaussians, with one "is any pixel still unsaturated" vote per batch
        while (k0 < end) & (live > 0):
            for k in range(k0, tl.minimum(k0 + BATCH, end)):
                # one Gaussian: scalar loads (every lane reads the same address), per-pixel math
                row = P + tl.load(tlist + k) * _PACK
                c = tl.load(row + 6) * dx + tl.load(row + 7) * dy + tl.load(row + 8) * dz
                ic = tl.math.rsqrt(c * c)  # = 1/c where c > 0, the only pixels kept (one MUFU, no range fix-up)
                u = (tl.load(row + 0) * dx + tl.load(row + 1) * dy + tl.load(row + 2) * dz) * ic - tl.load(row + 9)
                v = (tl.load(row + 3) * dx + tl.load(row + 4) * dy + tl.load(row + 5) * dz) * ic - tl.load(row + 10)
                # e = −power·log2(e): the conic and the cutoff scaled once per Gaussian, so that the
                # Gaussian is one exp2 and the cutoff test one compare
                e = ((tl.load(row + 11) * _NHALF_LOG2E) * u + (tl.load(row + 12) * _NLOG2E) * v) * u \
                    + (tl.load(row + 13) * _NHALF_LOG2E) * (v * v)
                keep = (c > _C_MIN) & (e >= tl.load(row + 19) * _NLOG2E)
                alpha = tl.minimum(tl.load(row + 14) * tl.exp2(e), _ALPHA_MAX)
                inc = keep & (T >= _T_MIN)  # a pixel stops after the Gaussian that saturates it
                w = tl.where(inc, alpha * T, 0.0)
                acc_r += w * tl.load(row + 15)
                acc_g += w * tl.load(row + 16)
                acc_b += w * tl.load(row + 17)
                acc_d += w * tl.load(row + 18)
                T -= w
                last = tl.where(inc, k, last)
            live = tl.reduce((T >= _T_MIN).to(tl.int32), 0, _elementwise_max)
            k0 += BATCH
        if HAS_BG:  # the background behind what is left of the transmittance
            acc_r += T * tl.load(bg)
            acc_g += T * tl.load(bg + 1)
            acc_b += T * tl.load(bg + 2)
        tl.store(out_color + pix * 3, acc_r, mask=pok)
        tl.store(out_color + pix * 3 + 1, acc_g, mask=pok)
        tl.store(out_color + pix * 3 + 2, acc_b, mask=pok)
        tl.store(out_depth + pix, acc_d, mask=pok)
        tl.store(out_T + pix, T, mask=pok)
        tl.store(out_T + npx + pix, 1.0 - T, mask=pok)  # the alpha channel, in the same buffer
        tl.store(out_last + pix, last, mask=pok)

    @triton.jit
    def _raster_bwd(P, dirs, toff, tlist, bg, T_final, last_k, g_color, g_depth, g_alpha, gP, H, W, TS,
                    SPLIT: tl.constexpr, BLOCK_PIX: tl.constexpr, HAS_G_DEPTH: tl.constexpr,
                    HAS_G_ALPHA: tl.constexpr, HAS_BG: tl.constexpr):
        tile, pix, pok = _tile_pixels(tl.program_id(0), H, W, TS, SPLIT, BLOCK_PIX)
        dx = tl.load(dirs + pix * 3, mask=pok, other=0)
        dy = tl.load(dirs + pix * 3 + 1, mask=pok, other=0)
        dz = tl.load(dirs + pix * 3 + 2, mask=pok, other=0)
        gCr = tl.load(g_color + pix * 3, mask=pok, other=0)
        gCg = tl.load(g_color + pix * 3 + 1, mask=pok, other=0)
        gCb = tl.load(g_color + pix * 3 + 2, mask=pok, other=0)
        # depth and alpha often have no gradient (a photometric loss alone): then the loop
        # neither loads nor sums their terms
        gD = dx * 0
        gA = dx * 0
        if HAS_G_DEPTH:
            gD = tl.load(g_depth + pix, mask=pok, other=0)
        if HAS_G_ALPHA:
            gA = tl.load(g_alpha + pix, mask=pok, other=0)
        if HAS_BG:
            # image = Σ w·c + (1 − Σ w)·bg: the background enters each Gaussian's contribution as
            # the alpha channel does, with the weight −bg·∂L/∂image
            gA -= gCr * tl.load(bg) + gCg * tl.load(bg + 1) + gCb * tl.load(bg + 2)
        T = tl.load(T_final + pix, mask=pok, other=1)  # transmittance behind the current Gaussian
        last = tl.load(last_k + pix, mask=pok, other=-1)
        behind = dx * 0  # Σ_{j behind} w_j x_j of the Gaussians already visited
        start = tl.load(toff + tile)
        kmax = tl.reduce(last, 0, _elementwise_max)
        # from the last blend of the program's pixels back to the tile's first entry
        for i in range(0, kmax - start + 1):
            k = kmax - i
            row = P + tl.load(tlist + k) * _PACK
            c = tl.load(row + 6) * dx + tl.load(row + 7) * dy + tl.load(row + 8) * dz
            front = c > _C_MIN
            ic = tl.where(front, tl.math.rsqrt(c * c), 0.0)  # 0 behind the plane: every product below stays finite
            p0 = (tl.load(row + 0) * dx + tl.load(row + 1) * dy + tl.load(row + 2) * dz) * ic
            p1 = (tl.load(row + 3) * dx + tl.load(row + 4) * dy + tl.load(row + 5) * dz) * ic
            u = p0 - tl.load(row + 9)
            v = p1 - tl.load(row + 10)
            q00 = tl.load(row + 11)
            q01 = tl.load(row + 12)
            q11 = tl.load(row + 13)
            e = ((q00 * _NHALF_LOG2E) * u + (q01 * _NLOG2E) * v) * u + (q11 * _NHALF_LOG2E) * (v * v)
            hit = front & (e >= tl.load(row + 19) * _NLOG2E) & (k <= last)
            if tl.reduce(hit.to(tl.int32), 0, _elementwise_max) > 0:  # uniform: skip a Gaussian missing every pixel
                G = tl.exp2(e)
                oG = tl.load(row + 14) * G
                alpha = tl.where(hit, tl.minimum(oG, _ALPHA_MAX), 0.0)
                ra = tl.math.rsqrt((1.0 - alpha) * (1.0 - alpha))  # 1/(1 − α), α ≤ 0.99
                T = T * ra  # the transmittance in front of this Gaussian
                w = alpha * T
                # dL/d(contribution) of the Gaussian at the pixel: colour, depth and alpha terms
                x = tl.load(row + 15) * gCr + tl.load(row + 16) * gCg + tl.load(row + 17) * gCb
                if HAS_G_DEPTH:
                    x += tl.load(row + 18) * gD
                if HAS_G_ALPHA or HAS_BG:
                    x += gA
                dLda = T * x - behind * ra
                behind += w * x
                # no gradient through the 0.99 clamp (docs/splatting.md)
                free = hit & (oG < _ALPHA_MAX)
                dpow = tl.where(free, -oG * dLda, 0.0)
                a = dpow * u
                b = dpow * v
                du = q00 * a + q01 * b
                dv = q01 * a + q11 * b
                dh0 = du * ic
                dh1 = dv * ic
                dc = -(dh0 * p0 + dh1 * p1)  # h = (u + uc)·c
                # sums over the program's pixels (one warp: shuffles, no barrier), gathered into one
                # vector (lane j holds parameter j) and added with one relaxed atomic per lane (no fence:
                # nothing reads gP before the kernel ends)
                j = tl.arange(0, 32)
                grad = tl.where(j == 0, tl.reduce(dh0 * dx, 0, _sum_combine), 0.0)
                grad = tl.where(j == 1, tl.reduce(dh0 * dy, 0, _sum_combine), grad)
                grad = tl.where(j == 2, tl.reduce(dh0 * dz, 0, _sum_combine), grad)
                grad = tl.where(j == 3, tl.reduce(dh1 * dx, 0, _sum_combine), grad)
                grad = tl.where(j == 4, tl.reduce(dh1 * dy, 0, _sum_combine), grad)
                grad = tl.where(j == 5, tl.reduce(dh1 * dz, 0, _sum_combine), grad)
                grad = tl.where(j == 6, tl.reduce(dc * dx, 0, _sum_combine), grad)
                grad = tl.where(j == 7, tl.reduce(dc * dy, 0, _sum_combine), grad)
                grad = tl.where(j == 8, tl.reduce(dc * dz, 0, _sum_combine), grad)
                grad = tl.where(j == 9, -tl.reduce(du, 0, _sum_combine), grad)
                grad = tl.where(j == 10, -tl.reduce(dv, 0, _sum_combine), grad)
                grad = tl.where(j == 11, 0.5 * tl.reduce(a * u, 0, _sum_combine), grad)
                grad = tl.where(j == 12, tl.reduce(a * v, 0, _sum_combine), grad)
                grad = tl.where(j == 13, 0.5 * tl.reduce(b * v, 0, _sum_combine), grad)
                grad = tl.where(j == 14, tl.reduce(tl.where(free, G * dLda, 0.0), 0, _sum_combine), grad)
                grad = tl.where(j == 15, tl.reduce(w * gCr, 0, _sum_combine), grad)
                grad = tl.where(j == 16, tl.reduce(w * gCg, 0, _sum_combine), grad)
                grad = tl.where(j == 17, tl.reduce(w * gCb, 0, _sum_combine), grad)
                if HAS_G_DEPTH:
                    grad = tl.where(j == 18, tl.reduce(w * gD, 0, _sum_combine), grad)
                tl.atomic_add(gP + tl.load(tlist + k) * _PACK + j, grad, mask=j < _PACK - 1, sem="relaxed")

def _interpreter_state():
    """(our kernels are interpreted, triton's library functions are interpreted)."""
    from triton.runtime.interpreter import InterpretedFunction

    return isinstance(_raster_fwd, InterpretedFunction), isinstance(tl.standard.sum, InterpretedFunction)


_INTERPRETED, _LIBRARY_INTERPRETED = _interpreter_state() if triton is not None else (False, False)


def interpreted() -> bool:
    """True if these kernels run in the Triton interpreter (``TRITON_INTERPRET=1`` when triton was imported)."""
    return _INTERPRETED


def unavailable_reason(device: torch.device):
    """Why the kernels cannot run on ``device`` (one line), or None if they can."""
    if triton is None:
        return f"triton is not installed ({_IMPORT_ERROR})"
    if _INTERPRETED != _LIBRARY_INTERPRETED:
        return ("TRITON_INTERPRET changed between the first import of triton and of splatting.raster_triton; "
                "set it before anything imports triton")
    if device.type == "cuda" or _INTERPRETED:
        return None
    return (f"backend='cuda' needs CUDA tensors (got {device.type}); set TRITON_INTERPRET=1 before importing "
            "triton to run its kernels on the CPU in the Triton interpreter")


def _config(kernel, H, W, ts, element_size):
    """grid, BLOCK_PIX and launch options of ``kernel`` ("forward" or "backward")."""
    warps, split = LAUNCH[(kernel, element_size)]
    if _INTERPRETED and not SPLIT_IN_INTERPRETER:
        split = 1  # the interpreter's cost is per operation, not per pixel: one program per tile
    ntiles = ((W + ts - 1) // ts) * ((H + ts - 1) // ts)
    block = max(1, triton.next_power_of_2(ts * ts) // split)
    return (ntiles * split,), dict(SPLIT=split, BLOCK_PIX=block, num_warps=warps)


def pairs_per_trip(kernel: str, ts: int, element_size: int) -> float:
    """Gaussian–pixel pairs one trip of the kernel's inner loop (one Gaussian) evaluates per
    thread; for the SASS count of splatting/kernel_report.py."""
    warps, split = LAUNCH[(kernel, element_size)]
    return max(1, triton.next_power_of_2(ts * ts) // split) / (32 * warps)


def forward_launch(P, dirs, toff, tlist, color, depth, T_alpha, last, H, W, ts, background=None):
    """(kernel, grid, args, constexprs and launch options) of the forward: the one place the
    launch is spelled out, used by :class:`TritonRaster` and by the compile check
    (splatting/kernel_report.py), so the check compiles what runs. `background` [3] or None
    (the colour is then the Gaussians' alone)."""
    grid, options = _config("forward", H, W, ts, P.element_size())
    bg = P if background is None else background  # any pointer: never read without its flag
    return (_raster_fwd, grid, (P, dirs, toff, tlist, bg, color, depth, T_alpha, last, H * W, H, W, ts),
            dict(BATCH=BATCH, HAS_BG=background is not None, **options))


def backward_launch(P, dirs, toff, tlist, T_final, last, g_color, g_depth, g_alpha, gP, H, W, ts, background=None):
    """As :func:`forward_launch`, for the backward; `g_depth` or `g_alpha` None: no gradient
    reaches that output (the kernel then skips its terms); `background` as the forward's."""
    grid, options = _config("backward", H, W, ts, P.element_size())
    flags = dict(HAS_G_DEPTH=g_depth is not None, HAS_G_ALPHA=g_alpha is not None, HAS_BG=background is not None)
    g_depth = g_color if g_depth is None else g_depth  # any pointer: never read without its flag
    g_alpha = g_color if g_alpha is None else g_alpha
    bg = P if background is None else background
    return (_raster_bwd, grid, (P, dirs, toff, tlist, bg, T_final, last, g_color, g_depth, g_alpha, gP, H, W, ts),
            dict(options, **flags))


def _launch(kernel, grid, args, options):
    kernel[grid](*args, **options)


def _index32(t):
    return t if t.dtype == torch.int32 else t.to(torch.int32)


class TritonRaster(torch.autograd.Function):
    """Same interface and math as :class:`splatting.raster_torch.TorchRaster`; the tile offsets
    and lists may be int64 (``bin_gaussians_torch``) or int32 (what the kernels index with).
    `background` ([3], no gradient) or None: the colour is composited over it in the kernel,
    which saves the three image-sized passes of the blend and their backward."""

    @staticmethod
    def forward(ctx, P, dirs, toff, tlist, H, W, ts, background=None):
        dtype, device = P.dtype, P.device
        P = P.contiguous()
        dirs = dirs.to(dtype).contiguous()
        toff, tlist = _index32(toff), _index32(tlist)
        npx = H * W
        # every pixel belongs to exactly one tile program, which writes all four outputs
        color = torch.empty(npx, 3, dtype=dtype, device=device)
        depth = torch.empty(npx, dtype=dtype, device=device)
        T_alpha = torch.empty(2, npx, dtype=dtype, device=device)  # final transmittance, 1 − it
        last = torch.empty(npx, dtype=torch.int32, device=device)
        if background is not None:
            background = background.to(dtype).contiguous()
        _launch(*forward_launch(P, dirs, toff, tlist, color, depth, T_alpha, last, H, W, ts, background))
        ctx.save_for_backward(P, dirs, toff, tlist, T_alpha[0], last, background)
        ctx.set_materialize_grads(False)  # an unused output's gradient stays None: no zeros to read
        ctx.dims = (H, W, ts)
        return color.reshape(H, W, 3), depth.reshape(H, W), T_alpha[1].reshape(H, W)

    @staticmethod
    def backward(ctx, g_color, g_depth, g_alpha):
        P, dirs, toff, tlist, T_final, last, background = ctx.saved_tensors
        H, W, ts = ctx.dims
        dtype, device = P.dtype, P.device

        def flat(g, shape):
            return None if g is None else g.to(dtype).reshape(shape).contiguous()

        g_color = torch.zeros((H * W, 3), dtype=dtype, device=device) if g_color is None else flat(g_color, (H * W, 3))
        gP = torch.zeros_like(P)
        _launch(*backward_launch(P, dirs, toff, tlist, T_final, last, g_color, flat(g_depth, (H * W,)),
                                 flat(g_alpha, (H * W,)), gP, H, W, ts, background))
        return gP, None, None, None, None, None, None, None

