"""Per-Gaussian projection onto its tangent plane (DESIGN.md "360° splatting").

Everything here is plain differentiable torch (O(N) work); the rasterisers only
see the packed per-Gaussian parameters built by :func:`project`.

Packed layout (``PACK`` columns per visible Gaussian), all in pixel units:
  0:3   a1 = s1·e1         (row of M: first tangent axis, scaled to pixels)
  3:6   a2 = s2·e2         (second tangent axis)
  6:9   n                  (unit normal of the tangent plane, camera frame)
  9:11  (uc, vc)           centre of the splat on the plane, pixels
  11:14 (Q00, Q01, Q11)    conic = inverse of the dilated 2D covariance, 1/pixel²
  14    opacity
  15:18 RGB colour
  18    distance ‖t‖       (sort key and depth value)
  19    tau                cutoff: skip a pixel where ½ pᵀQp > tau (no gradient)
For a pixel with ray direction d: h = M d, c = n·d (> 0 required),
u = h0/c − uc, v = h1/c − vc, alpha = min(o·exp(−½[u v]Q[u v]ᵀ), 0.99).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from .cameras import EquirectCamera

PACK = 20
ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_MIN = 1e-4
TAU_MAX = 4.5  # = ½·3², the 3σ cap of the opacity-aware radius
C_MIN = 1e-6  # n·d below this counts as "behind the tangent plane" (guards the 1/c)
# Front-to-back order: the distance's float32 bit pattern rounded to DEPTH_KEY_BITS mantissa bits
# (a relative step of 2⁻¹³, 0.6 mm at 5 m), ties in index order. Every backend computes the
# distance with its own rounding; at equal true distances (points on a sphere around the
# camera, a plane seen head-on) a last-bit difference would otherwise order the Gaussians
# differently per backend and change the image. Rounding (not truncating) puts the key's
# boundaries between round numbers, where exact ties sit.
DEPTH_KEY_BITS = 13
DEPTH_KEY_SHIFT = 23 - DEPTH_KEY_BITS


@dataclass
class Projection:
    packed: torch.Tensor  # [Nv, PACK] differentiable
    vis_idx: torch.Tensor  # [Nv] long, indices into the N Gaussians
    visible: torch.Tensor  # [N] bool
    radii: torch.Tensor  # [N] int32, pixels
    bbox: torch.Tensor  # [Nv, 4] int32: row0, row1 (inclusive), col0, ncols (cols wrap mod W)
    means2d: torch.Tensor  # [N, 2] leaf (see render.py)


def depth_key(dist: torch.Tensor) -> torch.Tensor:
    """int32 sort key of positive distances (see ``DEPTH_KEY_BITS``); the same rule as the
    ``cuda`` projection kernel and the C++ ``depth_order``."""
    bits = dist.detach().to(torch.float32).contiguous().view(torch.int32)
    return (bits + (1 << (DEPTH_KEY_SHIFT - 1))) >> DEPTH_KEY_SHIFT


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """(w, x, y, z), any norm -> [N,3,3]. The zero quaternion gives the identity."""
    n2 = (quats * quats).sum(-1, keepdim=True)
    q = quats * torch.rsqrt(torch.clamp(n2, min=1e-24))
    w, x, y, z = q.unbind(-1)
    R = torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    )
    return R.reshape(quats.shape[:-1] + (3, 3))


def onb(n: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Orthonormal tangent basis (e1, e2) of unit vectors n (Duff et al. 2017).

    Smooth with bounded derivatives everywhere except a switch at n_z = 0. The
    rendered image does not depend on the choice of basis (the quadratic form
    is invariant), so the switch changes nothing but rounding.
    """
    x, y, z = n.unbind(-1)
    sign = torch.where(z >= 0, torch.ones_like(z), -torch.ones_like(z))
    a = -1.0 / (sign + z)
    b = x * y * a
    e1 = torch.stack([1.0 + sign * x * x * a, sign * b, -sign * x], dim=-1)
    e2 = torch.stack([b, sign + y * y * a, -y], dim=-1)
    return e1, e2


def east_south(n: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Image-aligned tangent basis (east = +column, south = +row); no gradient needed.
    At the poles (undefined) east is taken as +x."""
    x, y, z = n.unbind(-1)
    h = torch.sqrt(x * x + z * z)
    ok = h > 1e-12
    hs = torch.where(ok, h, torch.ones_like(h))
    e = torch.stack([torch.where(ok, z / hs, torch.ones_like(h)), torch.zeros_like(h), torch.where(ok, -x / hs, torch.zeros_like(h))], -1)
    s = torch.cross(n, e, dim=-1)
    return e, s


def _equirect_bbox(n, hx, hy, camera: EquirectCamera):
    """Pixel box of the footprint of a splat centred on direction n (unit, camera frame).

    The footprint (ellipse) lies inside the rectangle |x| <= hx (east), |y| <= hy
    (north) of its tangent plane (tangent units). On the sphere, that rectangle is
    bounded exactly by (see docs/splatting.md):
      * no pole inside (hy < cot|theta0|): sin(theta) = (sin theta0 + y cos theta0)/sqrt(1+x²+y²)
        grows with y, so theta_max is at y = hy (x = 0, or x = hx when the numerator
        is negative), theta_min likewise at y = -hy; the longitude offset
        atan2(x, cos theta0 - y sin theta0) is largest at the corner x = hx,
        y = hy·sign(theta0);
      * a pole inside: every column, rows from theta0 ± atan(hypot(hx, hy)).
    Returns int tensors r0, r1, c0, ncols (columns wrap modulo W).
    """
    H, W = int(camera.height), int(camera.width)
    n = n.double()
    hx = hx.double()
    hy = hy.double()
    x, y, z = n.unbind(-1)
    hr = torch.sqrt(x * x + z * z)
    theta0 = torch.atan2(-y, hr)
    phi0 = torch.atan2(x, z)
    st, ct = -y, hr  # sin and cos of theta0
    pix = 2 * math.pi / W
    pole = hy * st.abs() >= ct  # theta0 + atan(hy) reaches a pole
    r = torch.sqrt(hx * hx + hy * hy)
    beta = torch.atan(r)
    num_hi = st + hy * ct
    num_lo = st - hy * ct
    den_hi = torch.where(num_hi >= 0, torch.sqrt(1 + hy * hy), torch.sqrt(1 + r * r))
    den_lo = torch.where(num_lo <= 0, torch.sqrt(1 + hy * hy), torch.sqrt(1 + r * r))
    s_hi = torch.clamp(num_hi / den_hi, -1.0, 1.0)
    s_lo = torch.clamp(num_lo / den_lo, -1.0, 1.0)
    # margins only absorb rounding (the kernels test every pixel exactly); atan(r) <= r
    margin = 1e-3 * pix + 1e-4 * r
    tmax = torch.where(pole, theta0 + beta, torch.asin(s_hi)) + margin
    tmin = torch.where(pole, theta0 - beta, torch.asin(s_lo)) - margin
    r0 = torch.ceil((0.5 - tmax / math.pi) * H - 0.5).clamp(0, H - 1)
    r1 = torch.floor((0.5 - tmin / math.pi) * H - 0.5).clamp(-1, H - 1)
    den = torch.clamp(ct - hy * st.abs(), min=1e-300)
    xr = hx / den  # small splats: xr >= atan(xr), larger by under 3.4e-4 rad (a cheap bound)
    dphi0 = torch.where(xr < 0.1, xr, torch.atan2(hx, den))
    # cos of the latitude bound farthest from the equator, from its sine (cos(t + m) >= cos t - m)
    smax = torch.maximum(s_hi.abs(), s_lo.abs())
    coslat = torch.clamp(torch.sqrt(torch.clamp(1 - smax * smax, min=0)) - margin, min=1e-12)
    dphi = dphi0 + 1e-4 * dphi0 + 1e-3 * pix / coslat
    full = pole | (tmax >= math.pi / 2) | (tmin <= -math.pi / 2) | (dphi >= math.pi)
    dphi = torch.clamp(dphi, max=math.pi)
    clo = torch.ceil(((phi0 - dphi) / (2 * math.pi) + 0.5) * W - 0.5)
    chi = torch.floor(((phi0 + dphi) / (2 * math.pi) + 0.5) * W - 0.5)
    ncol = chi - clo + 1
    full = full | (ncol >= W)
    empty = (ncol <= 0) & ~full
    clo = torch.where(full, torch.zeros_like(clo), torch.remainder(clo, W))
    ncol = torch.where(full, torch.full_like(ncol, W), ncol)
    r1 = torch.where(empty, r0 - 1, r1)  # no pixel centre inside: invisible
    return r0.long(), r1.long(), clo.long(), ncol.long()


def project(means, quats, scales, opacities, colors_rgb_fn, viewmat, camera, eps2d, near, extra_grad=(),
            keep: torch.Tensor | None = None) -> Projection:
    """Project N Gaussians; ``colors_rgb_fn(dirs_world [Nv,3], idx) -> [Nv,3]`` gives colours.

    ``keep`` ([N] bool, the visibility another projection already decided) asks for every row
    instead: ``packed`` is [N, PACK], rows outside ``keep`` computed from stand-in values (finite,
    so a zero gradient stays zero), ``vis_idx`` is None and ``bbox`` is not computed. Nothing then
    depends on the data's values for its shape: no ``nonzero``, no host sync (the ``cuda``
    backend's backward, splatting/project_triton.py)."""
    dtype, device = means.dtype, means.device
    N = means.shape[0]
    Rv = viewmat[:3, :3].to(dtype)
    tv = viewmat[:3, 3].to(dtype)
    t = means @ Rv.T + tv  # [N,3] camera frame
    eq = isinstance(camera, EquirectCamera)
    sx, sy = camera.pixel_scale
    dense = keep is not None

    with torch.no_grad():
        op = opacities.detach()
        if dense:
            valid = keep
        else:
            r2 = (t * t).sum(-1)
            valid = torch.isfinite(t).all(-1) & (r2 >= near * near) & (op > ALPHA_MIN)
            if not eq:
                valid = valid & (t[:, 2] >= near)
            valid = valid & (torch.isfinite(scales.detach()).all(-1) & torch.isfinite(quats.detach()).all(-1))
    if dense:  # stand-ins for the rows nobody sees: a small round splat, in front of the camera
        quats = torch.where(valid[:, None], quats, quats.new_tensor([1.0, 0.0, 0.0, 0.0]))
        scales = torch.where(valid[:, None], scales, scales.new_tensor(1e-2))
    safe_t = torch.tensor([0.0, 0.0, 1.0], dtype=dtype, device=device)
    ts = torch.where(valid[:, None], t, safe_t)
    dist = torch.sqrt(torch.clamp((ts * ts).sum(-1), min=1e-30))
    ndir = ts / dist[:, None]  # unit direction of the centre (camera frame)

    L = Rv @ quat_to_rotmat(quats) * scales[:, None, :]  # [N,3,3], Σc = L Lᵀ
    if eq:
        n = ndir
        e1, e2 = onb(n)
        T2 = torch.stack([e1 * (sx / dist[:, None]), e2 * (sy / dist[:, None])], dim=1)  # [N,2,3]
        uvc = torch.zeros(N, 2, dtype=dtype, device=device)
        a1, a2 = e1 * sx, e2 * sy
    else:
        z = ts[:, 2]
        one = torch.ones_like(z)
        zero = torch.zeros_like(z)
        n = torch.stack([zero, zero, one], -1)
        a1 = torch.stack([one * sx, zero, zero], -1)
        a2 = torch.stack([zero, one * sy, zero], -1)
        mx, my = ts[:, 0] / z, ts[:, 1] / z
        # as in 3DGS, the Jacobian is taken at the centre clamped to 1.3× the half field
        # of view, so splats far outside the image stay bounded (the centre is not clamped)
        limx = 1.3 * max(camera.cx, camera.width - camera.cx) / sx
        limy = 1.3 * max(camera.cy, camera.height - camera.cy) / sy
        jx, jy = torch.clamp(mx, -limx, limx), torch.clamp(my, -limy, limy)
        T2 = torch.stack(
            [torch.stack([sx / z, zero, -sx * jx / z], -1), torch.stack([zero, sy / z, -sy * jy / z], -1)], dim=1
        )
        uvc = torch.stack([sx * mx, sy * my], -1)
    M2 = T2 @ L  # [N,2,3]
    a0 = (M2[:, 0] ** 2).sum(-1)
    c0 = (M2[:, 1] ** 2).sum(-1)
    b = (M2[:, 0] * M2[:, 1]).sum(-1)
    m01 = M2[:, 0, 0] * M2[:, 1, 1] - M2[:, 0, 1] * M2[:, 1, 0]
    m02 = M2[:, 0, 0] * M2[:, 1, 2] - M2[:, 0, 2] * M2[:, 1, 0]
    m12 = M2[:, 0, 1] * M2[:, 1, 2] - M2[:, 0, 2] * M2[:, 1, 1]
    eps = float(eps2d)
    # det(M2 M2ᵀ + eps I) by Cauchy–Binet: a sum of non-negative terms, no cancellation.
    det = m01 * m01 + m02 * m02 + m12 * m12 + eps * (a0 + c0) + eps * eps
    a = a0 + eps
    c = c0 + eps
    if not dense:
        with torch.no_grad():
            tiny = torch.finfo(dtype).tiny * 1e6
            det_ok = torch.isfinite(det) & (det > tiny) & torch.isfinite(a) & torch.isfinite(c)
            valid = valid & (det_ok)
    det_s = torch.where(valid, det, torch.ones_like(det))
    Q = torch.stack([c / det_s, -b / det_s, a / det_s], -1)

    with torch.no_grad():
        tau = torch.clamp(torch.log(torch.clamp(op * 255.0, min=1e-30)), max=TAU_MAX).to(dtype)
        tau = torch.where(valid, tau, torch.zeros_like(tau))
        rot = None
        if eq:
            es_e, es_s = east_south(ndir.detach())
            e1d, e2d = e1.detach(), e2.detach()
            # rot maps an (east, south) offset to the (e1, e2) frame used by the rasteriser
            rot = torch.stack(
                [torch.stack([(e1d * es_e).sum(-1), (e1d * es_s).sum(-1)], -1),
                 torch.stack([(e2d * es_e).sum(-1), (e2d * es_s).sum(-1)], -1)], dim=1)
        if dense:
            vis_idx = radii = bbox = None
            m2d_val = torch.zeros(N, 2, dtype=dtype, device=device)  # a leaf for its gradient only
        else:
            vis_idx, radii, bbox, m2d_val, valid = _screen_footprint(
                camera, eq, valid, a, b, c, Q, tau, rot, ndir, uvc)
    need_grad = torch.is_grad_enabled() and any(
        x.requires_grad for x in (means, quats, scales, opacities, viewmat, *extra_grad)
    )
    means2d = m2d_val.clone().requires_grad_(need_grad)
    if need_grad:
        delta = means2d - means2d.detach()  # zero, with identity gradient
        if rot is not None:
            delta = (rot @ delta[:, :, None]).squeeze(-1)
        uvc = uvc + delta

    iv = slice(None) if dense else vis_idx
    dirs_world = ndir[iv] @ Rv  # camera -> world direction (Rvᵀ d, as row vectors)
    rgb = colors_rgb_fn(dirs_world, iv)
    packed = torch.cat(
        [
            a1[iv], a2[iv], n[iv], uvc[iv], Q[iv], opacities[iv, None].to(dtype), rgb.to(dtype),
            dist[iv, None], tau[iv, None],
        ],
        dim=-1,
    ).contiguous()
    return Projection(packed=packed, vis_idx=vis_idx, visible=valid, radii=radii, bbox=bbox, means2d=means2d)


def _screen_footprint(camera, eq, valid, a, b, c, Q, tau, rot, ndir, uvc):
    """What the rasteriser needs of each splat beyond its packed row (no gradient): the visible
    Gaussians' indices, radii and pixel boxes, the centres' pixel positions and the final
    visibility."""
    dtype, device = ndir.dtype, ndir.device
    sx, sy = camera.pixel_scale
    ad, bd, cd = a.detach(), b.detach(), c.detach()
    lmax = 0.5 * (ad + cd) + torch.sqrt(torch.clamp(0.25 * (ad - cd) ** 2 + bd * bd, min=0))
    radius = torch.sqrt(torch.clamp(2.0 * tau * lmax, min=0))
    valid = valid & (torch.isfinite(radius) & torch.isfinite(Q.detach()).all(-1))
    H, W = int(camera.height), int(camera.width)
    if eq:
        # the dilated covariance in the (east, south) frame: rotᵀ Σ rot
        see = rot[:, 0, 0] ** 2 * ad + 2 * rot[:, 0, 0] * rot[:, 1, 0] * bd + rot[:, 1, 0] ** 2 * cd
        sss = rot[:, 0, 1] ** 2 * ad + 2 * rot[:, 0, 1] * rot[:, 1, 1] * bd + rot[:, 1, 1] ** 2 * cd
        zero = torch.zeros_like(see)
        hx = torch.where(valid, torch.sqrt(torch.clamp(2.0 * tau * see, min=0)) / sx, zero)
        hy = torch.where(valid, torch.sqrt(torch.clamp(2.0 * tau * sss, min=0)) / sy, zero)
        r0, r1, cc0, ncol = _equirect_bbox(ndir.detach(), hx, hy, camera)
    else:
        px = uvc.detach()[:, 0] + camera.cx
        py = uvc.detach()[:, 1] + camera.cy
        hx = torch.sqrt(torch.clamp(2.0 * tau * ad, min=0))
        hy = torch.sqrt(torch.clamp(2.0 * tau * cd, min=0))
        big = float(4 * (H + W) + 16)
        mx_, my_ = 1e-3 + 1e-4 * hx, 1e-3 + 1e-4 * hy  # rounding margins
        xlo = torch.ceil(px - hx - mx_ - 0.5).clamp(-big, big)
        xhi = torch.floor(px + hx + mx_ - 0.5).clamp(-big, big)
        ylo = torch.ceil(py - hy - my_ - 0.5).clamp(-big, big)
        yhi = torch.floor(py + hy + my_ - 0.5).clamp(-big, big)
        valid = valid & ((xhi >= 0) & (xlo <= W - 1) & (yhi >= 0) & (ylo <= H - 1) & (xhi >= xlo) & (yhi >= ylo))
        r0 = ylo.clamp(0, H - 1).long()
        r1 = yhi.clamp(0, H - 1).long()
        cc0 = xlo.clamp(0, W - 1).long()
        ncol = (xhi.clamp(0, W - 1).long() - cc0 + 1)
    valid = valid & (r1 >= r0)
    vis_idx = torch.nonzero(valid, as_tuple=False).squeeze(1)
    radii = torch.where(valid, torch.ceil(radius), torch.zeros_like(radius)).to(torch.int32)
    bbox = torch.stack([r0, r1, cc0, ncol], -1)[vis_idx].to(torch.int32).contiguous()

    # means2d values: pixel position of the centre; gradient: tangent-plane offset in pixels.
    if eq:
        m2d_val = camera.dirs_to_pixels(ndir.detach())
    else:
        m2d_val = uvc.detach() + torch.tensor([camera.cx, camera.cy], dtype=dtype, device=device)
    return vis_idx, radii, bbox, m2d_val, valid
