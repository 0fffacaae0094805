"""Slow, obviously-correct references used by the tests and the benchmark.

* :func:`rasterize_dense` evaluates every (pixel, Gaussian) pair with plain
  autograd, no tiles, no bounding boxes: the rasterisers must match it.
* :func:`ray_max_alpha` is the *exact* ray–Gaussian evaluation (the maximum of
  the 3D Gaussian along each ray) that the tangent-plane splat approximates.
* :func:`tiles_reached` tests every pixel of a (tile, Gaussian) pair: the tile test's
  (splatting/bin_triton.py) reference.
"""

from __future__ import annotations

import torch

from .project import ALPHA_MAX, C_MIN, T_MIN, depth_key, quat_to_rotmat


def rasterize_dense(P: torch.Tensor, dirs: torch.Tensor):
    """Same contract as the backends: packed params [Nv,20], dirs [H,W,3] ->
    (color [H,W,3], depth [H,W], alpha [H,W]). O(H·W·Nv) memory."""
    H, W, _ = dirs.shape
    d = dirs.reshape(-1, 3)
    order = torch.argsort(depth_key(P[:, 18]), stable=True)
    g = P[order]
    c = d @ g[:, 6:9].T  # [Px, Nv]
    h0 = d @ g[:, 0:3].T
    h1 = d @ g[:, 3:6].T
    ok = c > C_MIN
    cs = torch.where(ok, c, torch.ones_like(c))
    u = h0 / cs - g[:, 9]
    v = h1 / cs - g[:, 10]
    power = 0.5 * (g[:, 11] * u * u + g[:, 13] * v * v) + g[:, 12] * u * v
    keep = ok & (power <= g[:, 19])
    oG = g[:, 14] * torch.exp(-torch.where(keep, power, torch.zeros_like(power)))
    alpha = torch.where(keep, torch.clamp(oG, max=ALPHA_MAX), torch.zeros_like(oG))
    with torch.no_grad():
        Tx = torch.cumprod(1.0 - alpha, dim=1)
        Tx = torch.cat([torch.ones_like(Tx[:, :1]), Tx[:, :-1]], dim=1)
        inc = Tx >= T_MIN
    alpha = torch.where(inc, alpha, torch.zeros_like(alpha))
    T = torch.cumprod(1.0 - alpha, dim=1)
    Tex = torch.cat([torch.ones_like(T[:, :1]), T[:, :-1]], dim=1)
    w = alpha * Tex
    color = w @ g[:, 15:18]
    depth = w @ g[:, 18]
    alpha_out = 1.0 - T[:, -1] if T.shape[1] else torch.zeros(d.shape[0], dtype=P.dtype)
    return color.reshape(H, W, 3), depth.reshape(H, W), alpha_out.reshape(H, W)


def ray_max_alpha(means_cam, quats, scales, opacities, dirs, Rv=None):
    """Exact evaluation: alpha of each Gaussian on each ray = o · max_s G(s·d).

    means_cam [N,3] in the camera frame, dirs [P,3] (unit), -> [P,N].
    ``Rv`` rotates the Gaussians' world orientation into the camera frame.
    """
    R = quat_to_rotmat(quats)
    if Rv is not None:
        R = Rv @ R
    Linv = (R / scales[:, None, :]).transpose(1, 2)  # Σ⁻¹ = Linvᵀ Linv, Linv = S⁻¹ Rᵀ
    a = torch.einsum("nij,pj->pni", Linv, dirs)  # S⁻¹Rᵀd
    b = torch.einsum("nij,nj->ni", Linv, means_cam)[None]  # S⁻¹Rᵀμ
    dd = (a * a).sum(-1)
    dm = (a * b).sum(-1)
    mm = (b * b).sum(-1)
    s = torch.clamp(dm / dd, min=0.0)  # only in front of the camera
    m2 = mm - 2 * s * dm + s * s * dd
    return opacities[None] * torch.exp(-0.5 * m2)


def tiles_reached(tiles: torch.Tensor, gids: torch.Tensor, packed: torch.Tensor, camera, ts: int,
                  slack: float = 0.0, chunk: int = 100_000) -> torch.Tensor:
    """[pairs] bool: whether tile ``tiles[k]`` (row-major, ``ts``-pixel tiles) holds a pixel centre
    where Gaussian ``gids[k]`` (a row of ``packed``) passes its cut-off, ½ pᵀQp ≤ τ·(1 + slack),
    every pixel tested in float64 (a positive slack is stricter on a test that must keep the tile)."""
    H, W = int(camera.height), int(camera.width)
    ntx, nty = (W + ts - 1) // ts, (H + ts - 1) // ts
    dirs = torch.zeros(nty * ts, ntx * ts, 3, dtype=torch.float64)
    dirs[:H, :W] = camera.pixel_dirs(torch.float64)
    inside = torch.zeros(nty * ts, ntx * ts, dtype=torch.bool)
    inside[:H, :W] = True
    tdirs = dirs.reshape(nty, ts, ntx, ts, 3).permute(0, 2, 1, 3, 4).reshape(ntx * nty, ts * ts, 3)
    tinside = inside.reshape(nty, ts, ntx, ts).permute(0, 2, 1, 3).reshape(ntx * nty, ts * ts)
    P = packed.detach().double().cpu()
    tiles, gids = tiles.long().cpu(), gids.long().cpu()
    out = torch.zeros(tiles.shape[0], dtype=torch.bool)
    for s in range(0, tiles.shape[0], chunk):
        r, t = P[gids[s:s + chunk]], tiles[s:s + chunk]
        d = tdirs[t]
        c = torch.einsum("bk,bpk->bp", r[:, 6:9], d)
        ic = torch.where(c > C_MIN, 1 / c.clamp_min(1e-300), torch.zeros_like(c))
        u = torch.einsum("bk,bpk->bp", r[:, 0:3], d) * ic - r[:, 9:10]
        v = torch.einsum("bk,bpk->bp", r[:, 3:6], d) * ic - r[:, 10:11]
        q = 0.5 * r[:, 11:12] * u * u + r[:, 12:13] * u * v + 0.5 * r[:, 13:14] * v * v
        out[s:s + chunk] = ((c > C_MIN) & (q <= r[:, 19:20] * (1 + slack)) & tinside[t]).any(1)
    return out
