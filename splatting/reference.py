"""Slow, obviously-correct references used by the tests and the benchmark.

* :func:`rasterize_dense` evaluates every (pixel, Gaussian) pair with plain
  autograd, no tiles, no bounding boxes: the rasterisers must match it.
* :func:`ray_max_alpha` is the *exact* ray–Gaussian evaluation (the maximum of
  the 3D Gaussian along each ray) that the tangent-plane splat approximates.
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
