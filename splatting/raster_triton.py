"""The ``cuda`` backend's tile rasteriser: Triton kernels, forward and backward.

Projection (:func:`splatting.project.project`), sorting and binning
(:func:`splatting.raster_torch.bin_gaussians_torch`) stay plain torch; these two
kernels replace :class:`splatting.raster_torch.TorchRaster` and implement exactly its
math (and the ``cpp`` kernel's): one program per tile, the tile's pixels as one block.

* Forward: the tile's list is walked front to back in chunks of ``CHUNK`` Gaussians.
  A chunk is evaluated as a [CHUNK, pixels] block; the transmittance inside the chunk
  is a cumulative product along the Gaussian axis, so the per-Gaussian loop of the
  CPU kernel becomes a few block operations. The program stops once every pixel of the
  tile is saturated (T < T_MIN). It writes colour, depth, the final transmittance and,
  per pixel, the list index of the last Gaussian blended: all the backward needs.
* Backward (as gsplat): the list is walked back to front from the tile's last blended
  entry; each pixel's transmittance is recovered from its final value by dividing by
  (1 − α) (a reverse cumulative product), the colour "behind" a Gaussian is a reverse
  cumulative sum. The per-(Gaussian, pixel) gradients are summed over the tile's
  pixels first, then added to the Gaussian's row with one atomic add per parameter.

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

CHUNK = 16  # Gaussians evaluated at once per tile (rows of the [CHUNK, pixels] block)

if triton is not None:
    _ALPHA_MAX = tl.constexpr(ALPHA_MAX)
    _C_MIN = tl.constexpr(C_MIN)
    _T_MIN = tl.constexpr(T_MIN)
    _PACK = tl.constexpr(PACK)

    @triton.jit
    def _tile_pixels(tile, H, W, TS, BLOCK_PIX: tl.constexpr):
        """Flat pixel index of each slot of the tile and whether it is inside the image."""
        ntx = (W + TS - 1) // TS
        i = tl.arange(0, BLOCK_PIX)
        row = (tile // ntx) * TS + i // TS
        col = (tile % ntx) * TS + i % TS
        ok = (i < TS * TS) & (row < H) & (col < W)
        return row * W + col, ok

    @triton.jit
    def _splat_eval(P, g, gok, dx, dy, dz, pok):
        """Evaluate a chunk of Gaussians (rows of packed ``P`` at indices ``g``) at the
        tile's pixels (ray directions ``dx, dy, dz``): tangent-plane offsets u, v, the
        power, 1/c and ``keep`` (in front of the plane and inside the cutoff),
        all [CHUNK, pixels]. Layout of P: splatting/project.py."""
        row = P + g * _PACK
        c = (tl.load(row + 6, mask=gok, other=0)[:, None] * dx[None, :]
             + tl.load(row + 7, mask=gok, other=0)[:, None] * dy[None, :]
             + tl.load(row + 8, mask=gok, other=0)[:, None] * dz[None, :])
        ok = gok[:, None] & pok[None, :] & (c > _C_MIN)
        ic = 1.0 / tl.where(ok, c, 1.0)
        h0 = (tl.load(row + 0, mask=gok, other=0)[:, None] * dx[None, :]
              + tl.load(row + 1, mask=gok, other=0)[:, None] * dy[None, :]
              + tl.load(row + 2, mask=gok, other=0)[:, None] * dz[None, :])
        h1 = (tl.load(row + 3, mask=gok, other=0)[:, None] * dx[None, :]
              + tl.load(row + 4, mask=gok, other=0)[:, None] * dy[None, :]
              + tl.load(row + 5, mask=gok, other=0)[:, None] * dz[None, :])
        u = h0 * ic - tl.load(row + 9, mask=gok, other=0)[:, None]
        v = h1 * ic - tl.load(row + 10, mask=gok, other=0)[:, None]
        q00 = tl.load(row + 11, mask=gok, other=0)[:, None]
        q01 = tl.load(row + 12, mask=gok, other=0)[:, None]
        q11 = tl.load(row + 13, mask=gok, other=0)[:, None]
        power = 0.5 * (q00 * u * u + q11 * v * v) + q01 * u * v
        keep = ok & (power <= tl.load(row + 19, mask=gok, other=0)[:, None])
        return u, v, power, ic, keep

    @triton.jit
    def _raster_fwd(P, dirs, toff, tlist, out_color, out_depth, out_T, out_last, H, W, TS,
                    CHUNK: tl.constexpr, BLOCK_PIX: tl.constexpr):
        tile = tl.program_id(0)
        pix, pok = _tile_pixels(tile, H, W, TS, BLOCK_PIX)
        dx = tl.load(dirs + pix * 3, mask=pok, other=0)
        dy = tl.load(dirs + pix * 3 + 1, mask=pok, other=0)
        dz = tl.load(dirs + pix * 3 + 2, mask=pok, other=0)
        zero = dx * 0  # the working dtype (float32 or float64)
        T = zero + 1.0
        acc_r, acc_g, acc_b, acc_d = zero, zero, zero, zero
        last = tl.full((BLOCK_PIX,), -1, tl.int64)
        k0 = tl.load(toff + tile)
        end = tl.load(toff + tile + 1)
        live = tl.sum((pok & (T >= _T_MIN)).to(tl.int32), axis=0)  # pixels not yet saturated
        while (k0 < end) & (live > 0):
            k = k0 + tl.arange(0, CHUNK)
            gok = k < end
            g = tl.load(tlist + k, mask=gok, other=0)
            u, v, power, ic, keep = _splat_eval(P, g, gok, dx, dy, dz, pok)
            row = P + g * _PACK
            oG = tl.load(row + 14, mask=gok, other=0)[:, None] * tl.exp(-tl.where(keep, power, 0.0))
            alpha = tl.where(keep, tl.minimum(oG, _ALPHA_MAX), 0.0)
            # transmittance before (Texcl) and after (Tincl) each Gaussian of the chunk
            Tincl = T[None, :] * tl.cumprod(1.0 - alpha, axis=0)
            Texcl = Tincl / (1.0 - alpha)
            inc = keep & (Texcl >= _T_MIN)  # a prefix of the chunk: Texcl only decreases
            w = tl.where(inc, alpha * Texcl, 0.0)
            acc_r += tl.sum(w * tl.load(row + 15, mask=gok, other=0)[:, None], axis=0)
            acc_g += tl.sum(w * tl.load(row + 16, mask=gok, other=0)[:, None], axis=0)
            acc_b += tl.sum(w * tl.load(row + 17, mask=gok, other=0)[:, None], axis=0)
            acc_d += tl.sum(w * tl.load(row + 18, mask=gok, other=0)[:, None], axis=0)
            T = tl.min(tl.where(inc, Tincl, T[None, :]), axis=0)
            last = tl.maximum(last, tl.max(tl.where(inc, k[:, None], -1), axis=0))
            live = tl.sum((pok & (T >= _T_MIN)).to(tl.int32), axis=0)
            k0 += CHUNK
        tl.store(out_color + pix * 3, acc_r, mask=pok)
        tl.store(out_color + pix * 3 + 1, acc_g, mask=pok)
        tl.store(out_color + pix * 3 + 2, acc_b, mask=pok)
        tl.store(out_depth + pix, acc_d, mask=pok)
        tl.store(out_T + pix, T, mask=pok)
        tl.store(out_last + pix, last, mask=pok)

    @triton.jit
    def _raster_bwd(P, dirs, toff, tlist, T_final, last_k, g_color, g_depth, g_alpha, gP, H, W, TS,
                    CHUNK: tl.constexpr, BLOCK_PIX: tl.constexpr):
        tile = tl.program_id(0)
        pix, pok = _tile_pixels(tile, H, W, TS, BLOCK_PIX)
        dx = tl.load(dirs + pix * 3, mask=pok, other=0)
        dy = tl.load(dirs + pix * 3 + 1, mask=pok, other=0)
        dz = tl.load(dirs + pix * 3 + 2, mask=pok, other=0)
        gCr = tl.load(g_color + pix * 3, mask=pok, other=0)
        gCg = tl.load(g_color + pix * 3 + 1, mask=pok, other=0)
        gCb = tl.load(g_color + pix * 3 + 2, mask=pok, other=0)
        gD = tl.load(g_depth + pix, mask=pok, other=0)
        gA = tl.load(g_alpha + pix, mask=pok, other=0)
        T = tl.load(T_final + pix, mask=pok, other=1)  # transmittance behind the current chunk
        last = tl.load(last_k + pix, mask=pok, other=-1)
        behind = dx * 0  # Σ_{j behind} w_j x_j of the Gaussians already visited
        start = tl.load(toff + tile)
        end = tl.load(toff + tile + 1)
        kmax = tl.max(last, axis=0)
        k0 = start + ((kmax - start) // CHUNK) * CHUNK  # the chunk holding the tile's last blend
        while (k0 >= start) & (kmax >= start):
            k = k0 + tl.arange(0, CHUNK)
            gok = k < end
            g = tl.load(tlist + k, mask=gok, other=0)
            row = P + g * _PACK
            u, v, power, ic, keep = _splat_eval(P, g, gok, dx, dy, dz, pok)
            hit = keep & (k[:, None] <= last[None, :])
            G = tl.exp(-tl.where(hit, power, 0.0))
            oG = tl.load(row + 14, mask=gok, other=0)[:, None] * G
            alpha = tl.where(hit, tl.minimum(oG, _ALPHA_MAX), 0.0)
            ioma = 1.0 / (1.0 - alpha)
            Texcl = T[None, :] * tl.cumprod(ioma, axis=0, reverse=True)
            w = alpha * Texcl
            cr = tl.load(row + 15, mask=gok, other=0)[:, None]
            cg = tl.load(row + 16, mask=gok, other=0)[:, None]
            cb = tl.load(row + 17, mask=gok, other=0)[:, None]
            dist = tl.load(row + 18, mask=gok, other=0)[:, None]
            # dL/d(contribution) of the Gaussian at the pixel: colour, depth and alpha terms
            x = cr * gCr[None, :] + cg * gCg[None, :] + cb * gCb[None, :] + dist * gD[None, :] + gA[None, :]
            wx = tl.where(hit, w * x, 0.0)
            wx_behind = behind[None, :] + (tl.cumsum(wx, axis=0, reverse=True) - wx)
            dLda = Texcl * x - wx_behind * ioma
            # no gradient through the 0.99 clamp (docs/splatting.md)
            free = hit & (oG < _ALPHA_MAX)
            dpow = tl.where(free, -oG * dLda, 0.0)
            q00 = tl.load(row + 11, mask=gok, other=0)[:, None]
            q01 = tl.load(row + 12, mask=gok, other=0)[:, None]
            q11 = tl.load(row + 13, mask=gok, other=0)[:, None]
            du = dpow * (q00 * u + q01 * v)
            dv = dpow * (q01 * u + q11 * v)
            dh0 = du * ic
            dh1 = dv * ic
            # h0 = (u + uc)·c, h1 = (v + vc)·c
            dc = -(dh0 * (u + tl.load(row + 9, mask=gok, other=0)[:, None])
                   + dh1 * (v + tl.load(row + 10, mask=gok, other=0)[:, None]))
            # sums over the tile's pixels, then one atomic add per parameter
            out = gP + g * _PACK
            upd = gok & (tl.sum(hit.to(tl.int32), axis=1) > 0)
            tl.atomic_add(out + 0, tl.sum(dh0 * dx[None, :], axis=1), mask=upd)
            tl.atomic_add(out + 1, tl.sum(dh0 * dy[None, :], axis=1), mask=upd)
            tl.atomic_add(out + 2, tl.sum(dh0 * dz[None, :], axis=1), mask=upd)
            tl.atomic_add(out + 3, tl.sum(dh1 * dx[None, :], axis=1), mask=upd)
            tl.atomic_add(out + 4, tl.sum(dh1 * dy[None, :], axis=1), mask=upd)
            tl.atomic_add(out + 5, tl.sum(dh1 * dz[None, :], axis=1), mask=upd)
            tl.atomic_add(out + 6, tl.sum(dc * dx[None, :], axis=1), mask=upd)
            tl.atomic_add(out + 7, tl.sum(dc * dy[None, :], axis=1), mask=upd)
            tl.atomic_add(out + 8, tl.sum(dc * dz[None, :], axis=1), mask=upd)
            tl.atomic_add(out + 9, -tl.sum(du, axis=1), mask=upd)
            tl.atomic_add(out + 10, -tl.sum(dv, axis=1), mask=upd)
            tl.atomic_add(out + 11, tl.sum(0.5 * dpow * u * u, axis=1), mask=upd)
            tl.atomic_add(out + 12, tl.sum(dpow * u * v, axis=1), mask=upd)
            tl.atomic_add(out + 13, tl.sum(0.5 * dpow * v * v, axis=1), mask=upd)
            tl.atomic_add(out + 14, tl.sum(tl.where(free, G * dLda, 0.0), axis=1), mask=upd)
            tl.atomic_add(out + 15, tl.sum(w * gCr[None, :], axis=1), mask=upd)
            tl.atomic_add(out + 16, tl.sum(w * gCg[None, :], axis=1), mask=upd)
            tl.atomic_add(out + 17, tl.sum(w * gCb[None, :], axis=1), mask=upd)
            tl.atomic_add(out + 18, tl.sum(w * gD[None, :], axis=1), mask=upd)
            behind += tl.sum(wx, axis=0)
            T = tl.max(Texcl, axis=0)  # = the chunk's first row: ioma >= 1, so the products only grow
            k0 -= CHUNK


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


def _grid_args(H, W, ts):
    ntiles = ((W + ts - 1) // ts) * ((H + ts - 1) // ts)
    return (ntiles,), triton.next_power_of_2(ts * ts)


class TritonRaster(torch.autograd.Function):
    """Same interface and math as :class:`splatting.raster_torch.TorchRaster`."""

    @staticmethod
    def forward(ctx, P, dirs, toff, tlist, H, W, ts):
        dtype, device = P.dtype, P.device
        P = P.contiguous()
        dirs = dirs.to(dtype).contiguous()
        npx = H * W
        color = torch.zeros(npx, 3, dtype=dtype, device=device)
        depth = torch.zeros(npx, dtype=dtype, device=device)
        T_final = torch.ones(npx, dtype=dtype, device=device)
        last = torch.full((npx,), -1, dtype=torch.int64, device=device)
        grid, block_pix = _grid_args(H, W, ts)
        _raster_fwd[grid](P, dirs, toff, tlist, color, depth, T_final, last, H, W, ts,
                          CHUNK=CHUNK, BLOCK_PIX=block_pix)
        ctx.save_for_backward(P, dirs, toff, tlist, T_final, last)
        ctx.dims = (H, W, ts)
        return color.reshape(H, W, 3), depth.reshape(H, W), (1.0 - T_final).reshape(H, W)

    @staticmethod
    def backward(ctx, g_color, g_depth, g_alpha):
        P, dirs, toff, tlist, T_final, last = ctx.saved_tensors
        H, W, ts = ctx.dims
        dtype, device = P.dtype, P.device

        def grad_or_zeros(g, shape):
            if g is None:
                return torch.zeros(shape, dtype=dtype, device=device)
            return g.to(dtype).reshape(shape).contiguous()

        gP = torch.zeros_like(P)
        grid, block_pix = _grid_args(H, W, ts)
        _raster_bwd[grid](P, dirs, toff, tlist, T_final, last, grad_or_zeros(g_color, (H * W, 3)),
                          grad_or_zeros(g_depth, (H * W,)), grad_or_zeros(g_alpha, (H * W,)), gP, H, W, ts,
                          CHUNK=CHUNK, BLOCK_PIX=block_pix)
        return gP, None, None, None, None, None, None
