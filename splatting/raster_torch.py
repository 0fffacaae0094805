"""Pure-torch tile rasteriser: the readable reference, and the CUDA path.

Tiles are processed in batches of similar list length as dense
[tiles, gaussians-in-tile, pixels-in-tile] tensors, so memory is O(pairs in a
batch); the backward is hand-written (it recomputes alpha from the inputs)
instead of letting autograd keep every intermediate.
"""

from __future__ import annotations

import torch

from .project import ALPHA_MAX, C_MIN, T_MIN, depth_key

BATCH_ELEMS = 1 << 21  # pair evaluations held at once


def bin_gaussians_torch(bbox: torch.Tensor, dist: torch.Tensor, H: int, W: int, ts: int):
    """Tile lists: (offsets [ntiles+1] int64, list [npairs] int64 of Gaussian indices,
    front to back within each tile: by ``depth_key(dist)``, ties in index order)."""
    device = bbox.device
    ntx, nty = (W + ts - 1) // ts, (H + ts - 1) // ts
    ntiles = ntx * nty
    nv = bbox.shape[0]
    if nv == 0:
        return torch.zeros(ntiles + 1, dtype=torch.long, device=device), torch.zeros(0, dtype=torch.long, device=device)
    b = bbox.long()
    tr0, tr1 = b[:, 0] // ts, b[:, 1] // ts
    # columns [c0, c0+n) wrap modulo W; W need not be a multiple of the tile size, so
    # the wrapped part [0, c0+n-W) starts again at tile 0: the tiles form one circular run
    # starting at tile c0//ts.
    tc0 = b[:, 2] // ts
    end = b[:, 2] + b[:, 3]
    wrap = end > W
    ntc = torch.where(wrap, ntx - tc0 + (end - W - 1) // ts + 1, (end - 1) // ts - tc0 + 1)
    ntc = torch.clamp(ntc, max=ntx)
    ntr = tr1 - tr0 + 1
    cnt = ntr * ntc
    gid = torch.repeat_interleave(torch.arange(nv, device=device), cnt)
    start = torch.cumsum(cnt, 0) - cnt
    local = torch.arange(gid.shape[0], device=device) - start[gid]
    tr = tr0[gid] + local // ntc[gid]
    tc = (tc0[gid] + local % ntc[gid]) % ntx
    tile = tr * ntx + tc
    rank = torch.empty(nv, dtype=torch.long, device=device)
    rank[torch.argsort(depth_key(dist), stable=True)] = torch.arange(nv, device=device)
    key = tile * nv + rank[gid]
    order = torch.argsort(key)
    tlist = gid[order]
    counts = torch.bincount(tile, minlength=ntiles)
    toff = torch.zeros(ntiles + 1, dtype=torch.long, device=device)
    toff[1:] = torch.cumsum(counts, 0)
    return toff, tlist


def _tile_pixels(H, W, ts, device):
    """[ntiles, ts*ts] flat pixel index per tile slot and validity mask."""
    ntx, nty = (W + ts - 1) // ts, (H + ts - 1) // ts
    ty = torch.arange(nty, device=device)[:, None, None, None]
    tx = torch.arange(ntx, device=device)[None, :, None, None]
    ly = torch.arange(ts, device=device)[None, None, :, None]
    lx = torch.arange(ts, device=device)[None, None, None, :]
    r = (ty * ts + ly).expand(nty, ntx, ts, ts)
    c = (tx * ts + lx).expand(nty, ntx, ts, ts)
    ok = (r < H) & (c < W)
    pix = torch.where(ok, r * W + c, torch.zeros_like(r))
    return pix.reshape(ntx * nty, ts * ts), ok.reshape(ntx * nty, ts * ts)


def _batches(toff):
    counts = (toff[1:] - toff[:-1]).cpu()
    order = torch.argsort(counts, descending=True)
    order = order[counts[order] > 0]
    i = 0
    n = order.shape[0]
    while i < n:
        L = int(counts[order[i]])
        B = max(1, BATCH_ELEMS // max(1, L * 256))
        yield order[i : i + B], L
        i += B


def _eval(P, dirs_flat, toff, tlist, tiles, L, pix_all, ok_all):
    """Recompute everything about one batch of tiles. Returns a dict of [B,L,P] tensors."""
    device = P.device
    tiles = tiles.to(device)
    start = toff[tiles]
    cnt = toff[tiles + 1] - start
    ar = torch.arange(L, device=device)
    gmask = ar[None, :] < cnt[:, None]  # [B,L]
    gidx = tlist[torch.where(gmask, start[:, None] + ar[None, :], torch.zeros_like(start[:, None]))]
    pix = pix_all[tiles]  # [B,Px]
    pmask = ok_all[tiles]
    g = P[gidx]  # [B,L,PACK]
    d = dirs_flat[pix]  # [B,Px,3]
    h0 = torch.einsum("blk,bpk->blp", g[..., 0:3], d)
    h1 = torch.einsum("blk,bpk->blp", g[..., 3:6], d)
    c = torch.einsum("blk,bpk->blp", g[..., 6:9], d)
    m = gmask[:, :, None] & pmask[:, None, :] & (c > C_MIN)
    cs = torch.where(m, c, torch.ones_like(c))
    ic = 1.0 / cs
    u = h0 * ic - g[..., 9:10]
    v = h1 * ic - g[..., 10:11]
    q00, q01, q11 = g[..., 11:12], g[..., 12:13], g[..., 13:14]
    power = 0.5 * (q00 * u * u + q11 * v * v) + q01 * u * v
    keep = m & (power <= g[..., 19:20])
    G = torch.exp(-torch.where(keep, power, torch.zeros_like(power)))
    oG = g[..., 14:15] * G
    alpha = torch.where(keep, torch.clamp(oG, max=ALPHA_MAX), torch.zeros_like(oG))
    one_m = 1.0 - alpha
    Tincl = torch.cumprod(one_m, dim=1)
    Texcl = torch.cat([torch.ones_like(Tincl[:, :1]), Tincl[:, :-1]], dim=1)
    inc = keep & (Texcl >= T_MIN)
    alpha = torch.where(inc, alpha, torch.zeros_like(alpha))
    w = alpha * Texcl
    return dict(gidx=gidx, gmask=gmask, pix=pix, pmask=pmask, g=g, d=d, h0=h0, h1=h1, ic=ic, u=u, v=v,
                G=G, oG=oG, alpha=alpha, inc=inc, Texcl=Texcl, w=w)


class TorchRaster(torch.autograd.Function):
    @staticmethod
    def forward(ctx, P, dirs, toff, tlist, H, W, ts):
        dtype, device = P.dtype, P.device
        npx = H * W
        color = torch.zeros(npx, 3, dtype=dtype, device=device)
        depth = torch.zeros(npx, dtype=dtype, device=device)
        Tfin = torch.ones(npx, dtype=dtype, device=device)
        dirs_flat = dirs.reshape(-1, 3)
        pix_all, ok_all = _tile_pixels(H, W, ts, device)
        with torch.no_grad():
            for tiles, L in _batches(toff):
                e = _eval(P, dirs_flat, toff, tlist, tiles, L, pix_all, ok_all)
                w, g = e["w"], e["g"]
                col = torch.einsum("blp,blk->bpk", w, g[..., 15:18])
                dep = torch.einsum("blp,bl->bp", w, g[..., 18])
                tf = torch.prod(1.0 - e["alpha"], dim=1)
                pm = e["pmask"]
                pix = e["pix"][pm]
                color[pix] = col[pm]
                depth[pix] = dep[pm]
                Tfin[pix] = tf[pm]
        ctx.save_for_backward(P, dirs, toff, tlist)
        ctx.dims = (H, W, ts)
        return color.reshape(H, W, 3), depth.reshape(H, W), (1.0 - Tfin).reshape(H, W)

    @staticmethod
    def backward(ctx, g_color, g_depth, g_alpha):
        P, dirs, toff, tlist = ctx.saved_tensors
        H, W, ts = ctx.dims
        dtype, device = P.dtype, P.device
        gP = torch.zeros_like(P)
        g_color = g_color.reshape(-1, 3).to(dtype)
        g_depth = g_depth.reshape(-1).to(dtype)
        g_alpha = g_alpha.reshape(-1).to(dtype)
        dirs_flat = dirs.reshape(-1, 3)
        pix_all, ok_all = _tile_pixels(H, W, ts, device)
        for tiles, L in _batches(toff):
            e = _eval(P, dirs_flat, toff, tlist, tiles, L, pix_all, ok_all)
            g, pix, w, alpha, inc = e["g"], e["pix"], e["w"], e["alpha"], e["inc"]
            pm = e["pmask"].to(dtype)
            gC = g_color[pix] * pm[..., None]  # [B,Px,3]
            gD = g_depth[pix] * pm
            gA = g_alpha[pix] * pm
            xg = torch.einsum("blk,bpk->blp", g[..., 15:18], gC) + g[..., 18:19] * gD[:, None, :] + gA[:, None, :]
            wx = w * xg
            Sg = torch.flip(torch.cumsum(torch.flip(wx, [1]), 1), [1]) - wx  # Σ_{j>i}
            dLda = torch.where(inc, e["Texcl"] * xg - Sg / (1.0 - alpha), torch.zeros_like(xg))
            free = inc & (e["oG"] < ALPHA_MAX)
            dpow = torch.where(free, -e["oG"] * dLda, torch.zeros_like(dLda))
            gp = torch.zeros(g.shape, dtype=dtype, device=device)
            gp[..., 14] = torch.where(free, e["G"] * dLda, torch.zeros_like(dLda)).sum(-1)
            gp[..., 15:18] = torch.einsum("blp,bpk->blk", w, gC)
            gp[..., 18] = torch.einsum("blp,bp->bl", w, gD)
            u, v, ic = e["u"], e["v"], e["ic"]
            q00, q01, q11 = g[..., 11:12], g[..., 12:13], g[..., 13:14]
            du = dpow * (q00 * u + q01 * v)
            dv = dpow * (q01 * u + q11 * v)
            gp[..., 11] = (0.5 * dpow * u * u).sum(-1)
            gp[..., 12] = (dpow * u * v).sum(-1)
            gp[..., 13] = (0.5 * dpow * v * v).sum(-1)
            gp[..., 9] = -du.sum(-1)
            gp[..., 10] = -dv.sum(-1)
            dh0 = du * ic
            dh1 = dv * ic
            dc = -(dh0 * e["h0"] + dh1 * e["h1"]) * ic
            d = e["d"]
            gp[..., 0:3] = torch.einsum("blp,bpk->blk", dh0, d)
            gp[..., 3:6] = torch.einsum("blp,bpk->blk", dh1, d)
            gp[..., 6:9] = torch.einsum("blp,bpk->blk", dc, d)
            gm = e["gmask"]
            gP.index_add_(0, e["gidx"][gm], gp[gm])
        return gP, None, None, None, None, None, None
