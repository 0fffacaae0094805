"""Perspective crops stitched into a panorama: the test render of the "3D-GS" baseline.

A :class:`~splatting.cameras.PerspectiveRig` (the paper's eight 120° crops, or the cube
faces) is rendered crop by crop with ordinary pinhole cameras; each panorama pixel is then
a blend of the crops that see its direction, each sampled bilinearly. A crop's weight is a
feather, (1 − u²)(1 − v²) with (u, v) the pixel's position on the crop's image plane scaled
to ±1 at its border: 1 at the crop centre, falling to 0 at its edge, so where crops overlap
the one seeing the direction closer to its centre dominates and no seam shows where a crop
ends. Cube faces only touch along their borders, so there every pixel has exactly one face
(with its full weight) and the stitch is the plain cubemap resampling.
"""

from __future__ import annotations

from typing import Optional

import torch

from .cameras import EquirectCamera, PerspectiveRig, cubemap_rig
from .render import DEFAULT_EPS2D, DEFAULT_TILE, RenderOutput, render

__all__ = ["stitch", "stitch_table", "render_stitched", "render_cubemap"]

_TABLES: dict = {}


def stitch_table(height: int, width: int, rig: PerspectiveRig, device="cpu") -> tuple[torch.Tensor, torch.Tensor]:
    """For each of the ``height`` × ``width`` panorama pixels (row-major), ``idx`` [P, T] into the
    rig's crops flattened to [K·S·S] and ``weights`` [P, T] (float64, summing to 1): T = 4 bilinear
    taps × the most crops any pixel blends. Raises ValueError if a direction lies in no crop."""
    key = (int(height), int(width), rig, str(device))
    if key in _TABLES:
        return _TABLES[key]
    S = int(rig.size)
    f = rig.camera.fx
    half = rig.tan_half_fov
    d = EquirectCamera(int(height), int(width)).pixel_dirs(dtype=torch.float64).reshape(-1, 3)
    v = torch.einsum("kij,pj->pki", rig.rotations(), d)  # [P,K,3] the directions in each crop's frame
    z = v[..., 2]
    zs = torch.where(z > 1e-9, z, torch.ones_like(z))  # behind a crop: any finite value, weight 0 below
    u, w = v[..., 0] / zs / half, v[..., 1] / zs / half
    inside = (z > 1e-9) & (u.abs() <= 1.0) & (w.abs() <= 1.0)
    # The feather; + a tiny constant so a direction exactly on a crop border still counts.
    feather = torch.where(inside, (1.0 - u * u) * (1.0 - w * w) + 1e-12, torch.zeros_like(u))
    uncovered = int((feather.sum(1) == 0).sum())
    if uncovered:
        raise ValueError(f"the {len(rig)} crops of {rig.fov_deg:g}° leave {uncovered} of {d.shape[0]} panorama "
                         "pixels unseen; add crops or widen their field of view")
    m = int(inside.sum(1).max())
    wt, crop = torch.topk(feather, m, dim=1)  # [P,M] the crops each pixel blends, heaviest first
    wt = wt / wt.sum(1, keepdim=True)
    rows = torch.arange(d.shape[0])[:, None]
    x = (f * u[rows, crop] * half + S / 2.0 - 0.5).clamp(0, S - 1)  # continuous pixel index in the crop
    y = (f * w[rows, crop] * half + S / 2.0 - 0.5).clamp(0, S - 1)
    x0 = torch.floor(x).clamp(max=max(S - 2, 0))
    y0 = torch.floor(y).clamp(max=max(S - 2, 0))
    fx, fy = x - x0, y - y0
    x0, y0 = x0.long(), y0.long()
    x1, y1 = (x0 + 1).clamp(max=S - 1), (y0 + 1).clamp(max=S - 1)
    base = crop * S * S
    idx = torch.stack([base + y0 * S + x0, base + y0 * S + x1, base + y1 * S + x0, base + y1 * S + x1], -1)
    wts = torch.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy], -1) * wt[..., None]
    out = (idx.reshape(d.shape[0], -1).to(device), wts.reshape(d.shape[0], -1).to(device))
    _TABLES[key] = out
    return out


def stitch(crops: torch.Tensor, height: int, width: int, rig: PerspectiveRig) -> torch.Tensor:
    """[K, S, S, C] images of the rig's crops -> [height, width, C] panorama (differentiable)."""
    K, S = len(rig), int(rig.size)
    if crops.shape[:3] != (K, S, S):
        raise ValueError(f"expected [{K},{S},{S},C] crops, got {list(crops.shape)}")
    idx, wts = stitch_table(height, width, rig, crops.device)
    wts = wts.to(crops.dtype)
    flat = crops.reshape(K * S * S, -1)
    # four (or 4·M) gathers and multiply-adds over one [K·S², C] table: measured 1.7× faster
    # than gathering [P,T,C] at once
    out = flat[idx[:, 0]] * wts[:, 0, None]
    for k in range(1, idx.shape[1]):
        out = out.addcmul(flat[idx[:, k]], wts[:, k, None])
    return out.reshape(int(height), int(width), -1)


def render_stitched(
    means, quats, scales, opacities, colors, viewmat, height: int, width: int, rig: PerspectiveRig,
    sh_degree=None, background=None, eps2d: float = DEFAULT_EPS2D, near: float = 0.05, backend=None,
    tile_size: int = DEFAULT_TILE,
):
    """Render every crop of ``rig`` with :func:`splatting.render` and stitch them into a
    ``height`` × ``width`` equirectangular image (colour, alpha and depth alike).

    A Gaussian is ``visible`` if any crop sees it, ``radii`` is the max over the crops, and
    ``means2d`` is a detached [K,N,2] stack of per-crop pixel positions; to train on crops with
    densification, render the crops of ``rig.crops()`` one by one with :func:`render` instead."""
    dtype, device = means.dtype, means.device
    viewmat = viewmat.to(device=device, dtype=dtype)
    outs = [render(means, quats, scales, opacities, colors, cv @ viewmat, cam, sh_degree=sh_degree,
                   background=background, eps2d=eps2d, near=near, backend=backend,
                   tile_size=tile_size)
            for cv, cam in rig.crops(dtype=dtype, device=device)]
    # colour, alpha and depth of all crops resampled in one pass
    crops = torch.stack([torch.cat([o.image, o.alpha[..., None], o.depth[..., None]], -1) for o in outs])
    pano = stitch(crops, height, width, rig)
    return RenderOutput(
        image=pano[..., :3], alpha=pano[..., 3], depth=pano[..., 4],
        means2d=torch.stack([o.means2d.detach() for o in outs]),
        radii=torch.stack([o.radii for o in outs]).max(0).values,
        visible=torch.stack([o.visible for o in outs]).any(0), backend=outs[-1].backend,
    )


def render_cubemap(
    means, quats, scales, opacities, colors, viewmat, height: int, width: int,
    sh_degree=None, background=None, eps2d: float = DEFAULT_EPS2D, near: float = 0.05, backend=None,
    face_size: Optional[int] = None, tile_size: int = DEFAULT_TILE,
):
    """The cubemap baseline: six 90° pinhole faces (``face_size``, default W/4) stitched into an
    equirectangular ``height`` × ``width`` image; :func:`render_stitched` with :func:`cubemap_rig`."""
    if face_size is None:
        face_size = max(2, int(round(width / 4)))
    return render_stitched(means, quats, scales, opacities, colors, viewmat, height, width, cubemap_rig(face_size),
                           sh_degree=sh_degree, background=background, eps2d=eps2d, near=near, backend=backend,
                           tile_size=tile_size)
