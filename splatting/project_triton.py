"""The ``cuda`` backend's projection: one Triton kernel instead of ~400 small torch operations.

:func:`splatting.project.project` (plain torch, the reference and the CPU path) launches a few
hundred element-wise kernels per render and compacts the visible Gaussians with ``nonzero``,
which makes the host wait for the device. Here one kernel computes, per Gaussian, exactly the
same quantities (same formulas, same order; DESIGN.md "360° splatting", docs/splatting.md):
the packed row, the tile box, the number of tiles it covers, the radius, the visibility and
the pixel position of the centre, for all N Gaussians at once. Rows of invalid Gaussians have
an empty box, so binning skips them and nothing is compacted; no shape depends on the data.

The box is computed in float64 like the reference, with the angles from a polynomial
``atan2`` (the interpreter cannot run libdevice; max error ~1e-8 rad, far below the
box's rounding margin, to which :data:`ANGLE_MARGIN` is added: the box stays conservative,
and the per-pixel test in the rasteriser is exact, so the image does not change).

Gradients: the backward recomputes the projection with the torch reference under autograd,
on every row with this kernel's visibility (``project(..., keep=visible)``: nothing compacted,
no host sync), and pulls the rasteriser's gradient of the packed rows through it (O(N), once
per step; docs/gpu.md).
"""

from __future__ import annotations

import math

import torch

from . import compile_ahead
from .cameras import EquirectCamera
from .devices import cdiv
from .optional_triton import tl, triton  # raster_triton reports a missing triton
from .project import ALPHA_MIN, DEPTH_KEY_SHIFT, PACK, TAU_MAX, project

ANGLE_MARGIN = 2e-6  # radians added to every angular bound of the box (covers the atan2 polynomial)
INTS = 7  # int32 columns per Gaussian: box (row0, row1, col0, ncols), tiles covered, radius, depth key

if triton is not None:
    _PI = tl.constexpr(math.pi)
    _HALF_PI = tl.constexpr(math.pi / 2)
    _QUARTER_PI = tl.constexpr(math.pi / 4)
    _TAN_PI_8 = tl.constexpr(math.tan(math.pi / 8))
    _ALPHA_MIN = tl.constexpr(ALPHA_MIN)
    _TAU_MAX = tl.constexpr(TAU_MAX)
    _ANGLE_MARGIN = tl.constexpr(ANGLE_MARGIN)
    _PACKW = tl.constexpr(PACK)
    _INTS = tl.constexpr(INTS)
    _DEPTH_KEY_SHIFT = tl.constexpr(DEPTH_KEY_SHIFT)
    _DEPTH_KEY_HALF = tl.constexpr(1 << (DEPTH_KEY_SHIFT - 1))
    _SH_C0 = tl.constexpr(0.28209479177387814)
    _SH_C1 = tl.constexpr(0.4886025119029199)

    @triton.jit
    def _depth_key(dist):
        """splatting.project.depth_key: float32 bits rounded to DEPTH_KEY_BITS mantissa bits."""
        bits = dist.to(tl.float32).to(tl.int32, bitcast=True)
        return (bits + _DEPTH_KEY_HALF) >> _DEPTH_KEY_SHIFT

    @triton.jit
    def _atan2(y, x):
        """atan2 from a polynomial (Cephes' atanf after two range reductions); |error| ≤ 1e-8 rad (measured)."""
        ax = tl.abs(x)
        ay = tl.abs(y)
        hi = tl.maximum(ax, ay)
        lo = tl.minimum(ax, ay)
        t = lo / tl.where(hi > 0, hi, 1.0)
        big = t > _TAN_PI_8
        t = tl.where(big, (t - 1.0) / (t + 1.0), t)
        z = t * t
        a = (((8.05374449538e-2 * z - 1.38776856032e-1) * z + 1.99777106478e-1) * z - 3.33329491539e-1) * z * t + t
        a = tl.where(big, a + _QUARTER_PI, a)
        a = tl.where(ay > ax, _HALF_PI - a, a)
        a = tl.where(x < 0, _PI - a, a)
        return tl.where(y < 0, -a, a)

    @triton.jit
    def _finite(x):
        return tl.abs(x) < float("inf")

    @triton.jit
    def _view_rotation(viewmat):
        """The rotation block of a row-major 4x4 world-to-camera matrix, row by row."""
        return (tl.load(viewmat + 0), tl.load(viewmat + 1), tl.load(viewmat + 2),
                tl.load(viewmat + 4), tl.load(viewmat + 5), tl.load(viewmat + 6),
                tl.load(viewmat + 8), tl.load(viewmat + 9), tl.load(viewmat + 10))

    @triton.jit
    def _unit_quat(qw, qx, qy, qz):
        """q / |q| and 1/|q| (|q|² floored at 1e-24: the zero quaternion gives the identity)."""
        inv = 1.0 / tl.sqrt(tl.maximum(qw * qw + qx * qx + qy * qy + qz * qz, 1e-24))
        return qw * inv, qx * inv, qy * inv, qz * inv, inv

    @triton.jit
    def _rotation(qw, qx, qy, qz):
        """R(q) of a unit quaternion, row by row."""
        return (1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qw * qz), 2 * (qx * qz + qw * qy),
                2 * (qx * qy + qw * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qw * qx),
                2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), 1 - 2 * (qx * qx + qy * qy))

    @triton.jit
    def _tangent_basis(nx, ny, nz):
        """Duff et al.'s basis (e1, e2) of the tangent plane at unit n, with its sign and
        a = −1/(sign + n_z) (the backward differentiates through them)."""
        sign = tl.where(nz >= 0, 1.0, -1.0)
        a = -1.0 / (sign + nz)
        b = nx * ny * a
        return sign, a, 1.0 + sign * nx * nx * a, sign * b, -sign * nx, b, sign + ny * ny * a, -ny

    # N not specialised (Triton's `% 16`): a per-Gaussian kernel gains nothing from it, and each
    # class of the count would compile again (3.4 s for SH 3 on sm_90) after a densification
    @triton.jit(do_not_specialize=["N"])
    def _project_fwd(means, quats, scales, opac, colors, viewmat, cam, packed, ints, visible, m2d, N, H, W, TS,
                     EQUIRECT: tl.constexpr, SH_DEGREE: tl.constexpr, K: tl.constexpr, BLOCK: tl.constexpr):
        i = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
        sx = tl.load(cam + 0)
        sy = tl.load(cam + 1)
        cx = tl.load(cam + 2)
        cy = tl.load(cam + 3)
        limx = tl.load(cam + 4)
        limy = tl.load(cam + 5)
        eps2d = tl.load(cam + 6)
        near = tl.load(cam + 7)
        tiny = tl.load(cam + 8)
        ok_i = i < N
        mx = tl.load(means + i * 3, mask=ok_i, other=0)
        my = tl.load(means + i * 3 + 1, mask=ok_i, other=0)
        mz = tl.load(means + i * 3 + 2, mask=ok_i, other=0)
        v00, v01, v02, v10, v11, v12, v20, v21, v22 = _view_rotation(viewmat)
        tx = mx * v00 + my * v01 + mz * v02 + tl.load(viewmat + 3)
        ty = mx * v10 + my * v11 + mz * v12 + tl.load(viewmat + 7)
        tz = mx * v20 + my * v21 + mz * v22 + tl.load(viewmat + 11)
        op = tl.load(opac + i, mask=ok_i, other=0)
        s0 = tl.load(scales + i * 3, mask=ok_i, other=0)
        s1 = tl.load(scales + i * 3 + 1, mask=ok_i, other=0)
        s2 = tl.load(scales + i * 3 + 2, mask=ok_i, other=0)
        qw = tl.load(quats + i * 4, mask=ok_i, other=0)
        qx = tl.load(quats + i * 4 + 1, mask=ok_i, other=0)
        qy = tl.load(quats + i * 4 + 2, mask=ok_i, other=0)
        qz = tl.load(quats + i * 4 + 3, mask=ok_i, other=0)
        r2 = tx * tx + ty * ty + tz * tz
        valid = ok_i & _finite(tx) & _finite(ty) & _finite(tz) & (r2 >= near * near) & (op > _ALPHA_MIN)
        if not EQUIRECT:
            valid = valid & (tz >= near)
        valid = valid & _finite(s0) & _finite(s1) & _finite(s2)
        valid = valid & _finite(qw) & _finite(qx) & _finite(qy) & _finite(qz)
        tx = tl.where(valid, tx, 0.0)
        ty = tl.where(valid, ty, 0.0)
        tz = tl.where(valid, tz, 1.0)
        dist = tl.sqrt(tl.maximum(tx * tx + ty * ty + tz * tz, 1e-30))
        nx = tx / dist
        ny = ty / dist
        nz = tz / dist
        qw, qx, qy, qz, _ = _unit_quat(qw, qx, qy, qz)
        q00, q01, q02, q10, q11, q12, q20, q21, q22 = _rotation(qw, qx, qy, qz)
        # L = Rv R(q) diag(s)
        L00 = (v00 * q00 + v01 * q10 + v02 * q20) * s0
        L01 = (v00 * q01 + v01 * q11 + v02 * q21) * s1
        L02 = (v00 * q02 + v01 * q12 + v02 * q22) * s2
        L10 = (v10 * q00 + v11 * q10 + v12 * q20) * s0
        L11 = (v10 * q01 + v11 * q11 + v12 * q21) * s1
        L12 = (v10 * q02 + v11 * q12 + v12 * q22) * s2
        L20 = (v20 * q00 + v21 * q10 + v22 * q20) * s0
        L21 = (v20 * q01 + v21 * q11 + v22 * q21) * s1
        L22 = (v20 * q02 + v21 * q12 + v22 * q22) * s2
        if EQUIRECT:
            _, _, e10, e11, e12, e20, e21, e22 = _tangent_basis(nx, ny, nz)
            k1 = sx / dist
            k2 = sy / dist
            T00 = e10 * k1
            T01 = e11 * k1
            T02 = e12 * k1
            T10 = e20 * k2
            T11 = e21 * k2
            T12 = e22 * k2
            a10 = e10 * sx
            a11 = e11 * sx
            a12 = e12 * sx
            a20 = e20 * sy
            a21 = e21 * sy
            a22 = e22 * sy
            pn0 = nx
            pn1 = ny
            pn2 = nz
            uc = nx * 0
            vc = nx * 0
        else:
            one = nx * 0 + 1.0
            zero = nx * 0
            pmx = tx / tz
            pmy = ty / tz
            jx = tl.minimum(tl.maximum(pmx, -limx), limx)
            jy = tl.minimum(tl.maximum(pmy, -limy), limy)
            T00 = sx / tz
            T01 = zero
            T02 = -sx * jx / tz
            T10 = zero
            T11 = sy / tz
            T12 = -sy * jy / tz
            a10 = one * sx
            a11 = zero
            a12 = zero
            a20 = zero
            a21 = one * sy
            a22 = zero
            pn0 = zero
            pn1 = zero
            pn2 = one
            uc = sx * pmx
            vc = sy * pmy
        M00 = T00 * L00 + T01 * L10 + T02 * L20
        M01 = T00 * L01 + T01 * L11 + T02 * L21
        M02 = T00 * L02 + T01 * L12 + T02 * L22
        M10 = T10 * L00 + T11 * L10 + T12 * L20
        M11 = T10 * L01 + T11 * L11 + T12 * L21
        M12 = T10 * L02 + T11 * L12 + T12 * L22
        a0 = M00 * M00 + M01 * M01 + M02 * M02
        c0 = M10 * M10 + M11 * M11 + M12 * M12
        bb = M00 * M10 + M01 * M11 + M02 * M12
        m01 = M00 * M11 - M01 * M10
        m02 = M00 * M12 - M02 * M10
        m12 = M01 * M12 - M02 * M11
        det = m01 * m01 + m02 * m02 + m12 * m12 + eps2d * (a0 + c0) + eps2d * eps2d
        aa = a0 + eps2d
        cc = c0 + eps2d
        valid = valid & _finite(det) & (det > tiny) & _finite(aa) & _finite(cc)
        det_s = tl.where(valid, det, 1.0)
        Q0 = cc / det_s
        Q1 = -bb / det_s
        Q2 = aa / det_s
        tau = tl.minimum(tl.log(tl.maximum(op * 255.0, 1e-30)), _TAU_MAX)
        tau = tl.where(valid, tau, 0.0)
        lmax = 0.5 * (aa + cc) + tl.sqrt(tl.maximum(0.25 * (aa - cc) * (aa - cc) + bb * bb, 0.0))
        radius = tl.sqrt(tl.maximum(2.0 * tau * lmax, 0.0))
        valid = valid & _finite(radius) & _finite(Q0) & _finite(Q1) & _finite(Q2)
        if EQUIRECT:
            # the box of the footprint on the sphere (project._equirect_bbox), in float64
            x = nx.to(tl.float64)
            y = ny.to(tl.float64)
            z = nz.to(tl.float64)
            hr = tl.sqrt(x * x + z * z)
            okh = hr > 1e-12
            hs = tl.where(okh, hr, 1.0)
            ee0 = tl.where(okh, z / hs, 1.0)
            ee2 = tl.where(okh, -x / hs, 0.0)
            # south = n × east (east has no y component)
            es0 = y * ee2
            es1 = z * ee0 - x * ee2
            es2 = -y * ee0
            r00 = a10.to(tl.float64) / sx * ee0 + a12.to(tl.float64) / sx * ee2
            r01 = (a10.to(tl.float64) * es0 + a11.to(tl.float64) * es1 + a12.to(tl.float64) * es2) / sx
            r10 = a20.to(tl.float64) / sy * ee0 + a22.to(tl.float64) / sy * ee2
            r11 = (a20.to(tl.float64) * es0 + a21.to(tl.float64) * es1 + a22.to(tl.float64) * es2) / sy
            ad = aa.to(tl.float64)
            bd = bb.to(tl.float64)
            cd = cc.to(tl.float64)
            taud = tau.to(tl.float64)
            see = r00 * r00 * ad + 2 * r00 * r10 * bd + r10 * r10 * cd
            sss = r01 * r01 * ad + 2 * r01 * r11 * bd + r11 * r11 * cd
            hx = tl.where(valid, tl.sqrt(tl.maximum(2.0 * taud * see, 0.0)) / sx, 0.0)
            hy = tl.where(valid, tl.sqrt(tl.maximum(2.0 * taud * sss, 0.0)) / sy, 0.0)
            theta0 = _atan2(-y, hr)
            phi0 = _atan2(x, z)
            st = -y
            ct = hr
            pix = 2 * _PI / W
            pole = hy * tl.abs(st) >= ct
            rr = tl.sqrt(hx * hx + hy * hy)
            beta = _atan2(rr, rr * 0 + 1.0)
            num_hi = st + hy * ct
            num_lo = st - hy * ct
            den_hi = tl.where(num_hi >= 0, tl.sqrt(1 + hy * hy), tl.sqrt(1 + rr * rr))
            den_lo = tl.where(num_lo <= 0, tl.sqrt(1 + hy * hy), tl.sqrt(1 + rr * rr))
            s_hi = tl.minimum(tl.maximum(num_hi / den_hi, -1.0), 1.0)
            s_lo = tl.minimum(tl.maximum(num_lo / den_lo, -1.0), 1.0)
            margin = 1e-3 * pix + 1e-4 * rr + _ANGLE_MARGIN
            tmax = tl.where(pole, theta0 + beta, _atan2(s_hi, tl.sqrt(tl.maximum(1 - s_hi * s_hi, 0.0)))) + margin
            tmin = tl.where(pole, theta0 - beta, _atan2(s_lo, tl.sqrt(tl.maximum(1 - s_lo * s_lo, 0.0)))) - margin
            r0 = tl.minimum(tl.maximum(tl.ceil((0.5 - tmax / _PI) * H - 0.5), 0.0), H - 1.0)
            r1 = tl.minimum(tl.maximum(tl.floor((0.5 - tmin / _PI) * H - 0.5), -1.0), H - 1.0)
            den = tl.maximum(ct - hy * tl.abs(st), 1e-300)
            xr = hx / den
            dphi0 = tl.where(xr < 0.1, xr, _atan2(hx, den))
            smax = tl.maximum(tl.abs(s_hi), tl.abs(s_lo))
            coslat = tl.maximum(tl.sqrt(tl.maximum(1 - smax * smax, 0.0)) - margin, 1e-12)
            dphi = dphi0 + 1e-4 * dphi0 + 1e-3 * pix / coslat + _ANGLE_MARGIN
            full = pole | (tmax >= _HALF_PI) | (tmin <= -_HALF_PI) | (dphi >= _PI)
            dphi = tl.minimum(dphi, _PI)
            clo = tl.ceil(((phi0 - dphi) / (2 * _PI) + 0.5) * W - 0.5)
            chi = tl.floor(((phi0 + dphi) / (2 * _PI) + 0.5) * W - 0.5)
            ncol = chi - clo + 1
            full = full | (ncol >= W)
            empty = (ncol <= 0) & (~full)
            clo = tl.where(full, 0.0, clo - tl.floor(clo / W) * W)
            ncol = tl.where(full, W * 1.0, ncol)
            r1 = tl.where(empty, r0 - 1, r1)
            # the centre's pixel position (DESIGN.md mapping)
            m2x = (phi0 / (2 * _PI) + 0.5) * W - 0.5
            m2y = (0.5 - theta0 / _PI) * H - 0.5
        else:
            px = uc + cx
            py = vc + cy
            hx = tl.sqrt(tl.maximum(2.0 * tau * aa, 0.0))
            hy = tl.sqrt(tl.maximum(2.0 * tau * cc, 0.0))
            big = 4.0 * (H + W) + 16
            mgx = 1e-3 + 1e-4 * hx
            mgy = 1e-3 + 1e-4 * hy
            xlo = tl.minimum(tl.maximum(tl.ceil(px - hx - mgx - 0.5), -big), big)
            xhi = tl.minimum(tl.maximum(tl.floor(px + hx + mgx - 0.5), -big), big)
            ylo = tl.minimum(tl.maximum(tl.ceil(py - hy - mgy - 0.5), -big), big)
            yhi = tl.minimum(tl.maximum(tl.floor(py + hy + mgy - 0.5), -big), big)
            valid = valid & (xhi >= 0) & (xlo <= W - 1) & (yhi >= 0) & (ylo <= H - 1) & (xhi >= xlo) & (yhi >= ylo)
            r0 = tl.minimum(tl.maximum(ylo, 0.0), H - 1.0)
            r1 = tl.minimum(tl.maximum(yhi, 0.0), H - 1.0)
            clo = tl.minimum(tl.maximum(xlo, 0.0), W - 1.0)
            ncol = tl.minimum(tl.maximum(xhi, 0.0), W - 1.0) - clo + 1
            m2x = px
            m2y = py
        valid = valid & (r1 >= r0)
        # integer box; an invalid Gaussian gets no rows (binning skips it)
        r0i = tl.where(valid, r0, 0.0).to(tl.int32)
        r1i = tl.where(valid, r1, -1.0).to(tl.int32)
        c0i = tl.where(valid, clo, 0.0).to(tl.int32)
        nci = tl.where(valid, ncol, 0.0).to(tl.int32)
        ntx = (W + TS - 1) // TS
        tc0 = c0i // TS
        cend = c0i + nci
        ntc = tl.where(cend > W, ntx - tc0 + (cend - W - 1) // TS + 1, (cend - 1) // TS - tc0 + 1)
        ntc = tl.minimum(ntc, ntx)
        ntr = tl.where(valid, r1i // TS - r0i // TS + 1, 0)
        ib = ints + i * _INTS
        tl.store(ib, r0i, mask=ok_i)
        tl.store(ib + 1, r1i, mask=ok_i)
        tl.store(ib + 2, c0i, mask=ok_i)
        tl.store(ib + 3, nci, mask=ok_i)
        tl.store(ib + 4, tl.where(valid, ntr * ntc, 0), mask=ok_i)
        tl.store(ib + 5, tl.where(valid, tl.ceil(radius), 0.0).to(tl.int32), mask=ok_i)
        tl.store(ib + 6, _depth_key(dist), mask=ok_i)
        tl.store(visible + i, valid, mask=ok_i)
        tl.store(m2d + i * 2, m2x.to(m2d.dtype.element_ty), mask=ok_i)
        tl.store(m2d + i * 2 + 1, m2y.to(m2d.dtype.element_ty), mask=ok_i)
        # colour: RGB, or SH seen along the world direction of the centre (Rvᵀ n)
        if SH_DEGREE < 0:
            cr = tl.load(colors + i * 3, mask=ok_i, other=0)
            cg = tl.load(colors + i * 3 + 1, mask=ok_i, other=0)
            cb = tl.load(colors + i * 3 + 2, mask=ok_i, other=0)
        else:
            wx = nx * v00 + ny * v10 + nz * v20
            wy = nx * v01 + ny * v11 + nz * v21
            wz = nx * v02 + ny * v12 + nz * v22
            cr = _sh_channel(colors, i, ok_i, wx, wy, wz, 0, SH_DEGREE, K)
            cg = _sh_channel(colors, i, ok_i, wx, wy, wz, 1, SH_DEGREE, K)
            cb = _sh_channel(colors, i, ok_i, wx, wy, wz, 2, SH_DEGREE, K)
            cr = tl.maximum(cr + 0.5, 0.0)
            cg = tl.maximum(cg + 0.5, 0.0)
            cb = tl.maximum(cb + 0.5, 0.0)
        row = packed + i * _PACKW
        tl.store(row + 0, a10, mask=ok_i)
        tl.store(row + 1, a11, mask=ok_i)
        tl.store(row + 2, a12, mask=ok_i)
        tl.store(row + 3, a20, mask=ok_i)
        tl.store(row + 4, a21, mask=ok_i)
        tl.store(row + 5, a22, mask=ok_i)
        tl.store(row + 6, pn0, mask=ok_i)
        tl.store(row + 7, pn1, mask=ok_i)
        tl.store(row + 8, pn2, mask=ok_i)
        tl.store(row + 9, uc, mask=ok_i)
        tl.store(row + 10, vc, mask=ok_i)
        tl.store(row + 11, Q0, mask=ok_i)
        tl.store(row + 12, Q1, mask=ok_i)
        tl.store(row + 13, Q2, mask=ok_i)
        tl.store(row + 14, op, mask=ok_i)
        tl.store(row + 15, cr, mask=ok_i)
        tl.store(row + 16, cg, mask=ok_i)
        tl.store(row + 17, cb, mask=ok_i)
        tl.store(row + 18, dist, mask=ok_i)
        tl.store(row + 19, tau, mask=ok_i)

    @triton.jit
    def _sh_channel(colors, i, ok_i, x, y, z, ch: tl.constexpr, DEG: tl.constexpr, K: tl.constexpr):
        """One colour channel of real SH (splatting/sh.py: 3DGS constants and signs), degree DEG."""
        base = colors + i * (K * 3) + ch
        res = _SH_C0 * tl.load(base, mask=ok_i, other=0)
        if DEG > 0:
            rn = 1.0 / tl.sqrt(tl.maximum(x * x + y * y + z * z, 1e-30))
            x = x * rn
            y = y * rn
            z = z * rn
            res = res - _SH_C1 * y * tl.load(base + 3, mask=ok_i, other=0) \
                + _SH_C1 * z * tl.load(base + 6, mask=ok_i, other=0) - _SH_C1 * x * tl.load(base + 9, mask=ok_i, other=0)
            if DEG > 1:
                xx = x * x
                yy = y * y
                zz = z * z
                res = res + 1.0925484305920792 * (x * y) * tl.load(base + 12, mask=ok_i, other=0) \
                    + -1.0925484305920792 * (y * z) * tl.load(base + 15, mask=ok_i, other=0) \
                    + 0.31539156525252005 * (2.0 * zz - xx - yy) * tl.load(base + 18, mask=ok_i, other=0) \
                    + -1.0925484305920792 * (x * z) * tl.load(base + 21, mask=ok_i, other=0) \
                    + 0.5462742152960396 * (xx - yy) * tl.load(base + 24, mask=ok_i, other=0)
                if DEG > 2:
                    res = res + -0.5900435899266435 * y * (3 * xx - yy) * tl.load(base + 27, mask=ok_i, other=0) \
                        + 2.890611442640554 * (x * y) * z * tl.load(base + 30, mask=ok_i, other=0) \
                        + -0.4570457994644658 * y * (4 * zz - xx - yy) * tl.load(base + 33, mask=ok_i, other=0) \
                        + 0.3731763325901154 * z * (2 * zz - 3 * xx - 3 * yy) * tl.load(base + 36, mask=ok_i, other=0) \
                        + -0.4570457994644658 * x * (4 * zz - xx - yy) * tl.load(base + 39, mask=ok_i, other=0) \
                        + 1.445305721320277 * z * (xx - yy) * tl.load(base + 42, mask=ok_i, other=0) \
                        + -0.5900435899266435 * x * (xx - 3 * yy) * tl.load(base + 45, mask=ok_i, other=0)
        return res


_CAMERA_CACHE: dict = {}


def _camera_vector(camera, eps2d, near, dtype, device):
    """sx, sy, cx, cy, limx, limy, eps2d, near, tiny as a device tensor of the working dtype
    (kernel scalars would be float32), built once per camera."""
    key = (camera, float(eps2d), float(near), dtype, str(device))
    vec = _CAMERA_CACHE.get(key)
    if vec is None:
        sx, sy = camera.pixel_scale
        if isinstance(camera, EquirectCamera):
            cx = cy = limx = limy = 0.0
        else:
            cx, cy = float(camera.cx), float(camera.cy)
            limx = 1.3 * max(camera.cx, camera.width - camera.cx) / sx
            limy = 1.3 * max(camera.cy, camera.height - camera.cy) / sy
        tiny = torch.finfo(dtype).tiny * 1e6
        if len(_CAMERA_CACHE) >= 16:
            _CAMERA_CACHE.clear()
        vec = _CAMERA_CACHE[key] = torch.tensor([sx, sy, cx, cy, limx, limy, eps2d, near, tiny], dtype=dtype,
                                                device=device)
    return vec


BLOCK = 64  # Gaussians per program of the projection kernel


def projection_launch(means, quats, scales, opac, colors, viewmat, camvec, packed, ints, visible, m2d, H, W, ts,
                      equirect, sh_degree, K):
    """(kernel, grid, args, options) of the projection, for the launch and the compile check."""
    N = means.shape[0]
    grid = (max(1, cdiv(N, BLOCK)),)
    return (_project_fwd, grid, (means, quats, scales, opac, colors, viewmat, camvec, packed, ints, visible, m2d,
                                 N, H, W, ts),
            dict(EQUIRECT=bool(equirect), SH_DEGREE=int(sh_degree), K=int(K), BLOCK=BLOCK, num_warps=2))


class TritonProject(torch.autograd.Function):
    """Forward: the projection kernel. Backward: its gradient kernel
    (splatting/project_triton_backward.py); ``REFERENCE_BACKWARD`` swaps in the torch reference
    (splatting.project.project recomputed under autograd on every row, with the kernel's
    visibility), which the tests compare the kernel with."""

    REFERENCE_BACKWARD = False

    @staticmethod
    def forward(ctx, means, quats, scales, opac, colors, viewmat, means2d, camera, eps2d, near, sh_degree, ts,
                color_fn_factory):
        dtype, device = means.dtype, means.device
        N = means.shape[0]
        H, W = int(camera.height), int(camera.width)
        packed = torch.empty(N, PACK, dtype=dtype, device=device)
        ints = torch.empty(N, INTS, dtype=torch.int32, device=device)
        visible = torch.empty(N, dtype=torch.bool, device=device)
        K = colors.shape[1] if colors.dim() == 3 else 1
        deg = -1 if colors.dim() == 2 else int(sh_degree)
        camvec = _camera_vector(camera, eps2d, near, dtype, device)
        if N:
            kernel, grid, args, options = projection_launch(
                means.contiguous(), quats.contiguous(), scales.contiguous(), opac.contiguous(), colors.contiguous(),
                viewmat.contiguous(), camvec, packed, ints, visible, means2d.detach(), H, W, ts,
                isinstance(camera, EquirectCamera), deg, K)
            compile_ahead.launch(kernel, grid, args, options)  # with the later SH degrees' compiles, if asked
        ctx.save_for_backward(means, quats, scales, opac, colors, viewmat, visible)
        ctx.setup = (camera, eps2d, near, sh_degree, color_fn_factory)
        ctx.mark_non_differentiable(ints, visible)
        ctx.set_materialize_grads(False)  # the integer outputs' gradients stay None: no zeros made
        return packed, ints, visible

    @staticmethod
    def backward(ctx, g_packed, _g_ints, _g_visible):
        means, quats, scales, opac, colors, viewmat, visible = ctx.saved_tensors
        camera, eps2d, near, sh_degree, color_fn_factory = ctx.setup
        if g_packed is None:
            return (None,) * 13
        if TritonProject.REFERENCE_BACKWARD:
            grads = _reference_backward(means, quats, scales, opac, colors, viewmat, visible, g_packed, camera, eps2d,
                                        near, sh_degree, color_fn_factory)
        else:
            from .project_triton_backward import project_backward

            grads = project_backward(means, quats, scales, colors, viewmat, visible, g_packed, camera, eps2d, near,
                                     sh_degree, view_grad=ctx.needs_input_grad[5])
        return (*grads, None, None, None, None, None, None)


def _reference_backward(means, quats, scales, opac, colors, viewmat, visible, g_packed, camera, eps2d, near, sh_degree,
                        color_fn_factory):
    """The projection's gradient by autograd through the torch reference: every row, the kernel's
    visibility given (no compaction, so no nonzero and no host sync; the rows it did not bin get
    a zero gradient from the rasteriser). Grads in the order of project_backward's."""
    inputs = [t.detach().requires_grad_(True) for t in (means, quats, scales, opac, colors, viewmat)]
    with torch.enable_grad():
        m, q, s, o, c, v = inputs
        proj = project(m, q, s, o, color_fn_factory(c, sh_degree, m.shape[0]), v, camera, eps2d, near, keep=visible)
        grads = torch.autograd.grad(proj.packed, inputs + [proj.means2d], g_packed, allow_unused=True)
    return [torch.zeros_like(x) if g is None else g for x, g in zip(inputs + [proj.means2d], grads)]


def project_gaussians(means, quats, scales, opacities, colors, viewmat, camera, eps2d, near, sh_degree, ts,
                      color_fn_factory):
    """The projection of the ``cuda`` backend: (packed [N, PACK], ints [N, INTS], visible [N] bool,
    means2d [N, 2] leaf). ``colors`` RGB [N,3] or SH [N,K,3] (``sh_degree`` resolved)."""
    N = means.shape[0]
    need_grad = torch.is_grad_enabled() and any(
        x.requires_grad for x in (means, quats, scales, opacities, colors, viewmat))
    means2d = torch.empty(N, 2, dtype=means.dtype, device=means.device).requires_grad_(need_grad)
    packed, ints, visible = TritonProject.apply(means, quats, scales, opacities, colors, viewmat, means2d, camera,
                                                eps2d, near, sh_degree, ts, color_fn_factory)
    return packed, ints, visible, means2d
