"""The ``cuda`` backend's projection gradient in one Triton kernel.

Per Gaussian, from the packed rows' gradient ``gP`` [N, PACK] (splatting/project.py's layout)
to the gradients of means, quaternions, scales, opacities, colours (RGB or SH coefficients),
the centres' pixel positions (``means2d``) and the view matrix. The math is the hand-written
backward of the ``cpp`` kernel (splatting/csrc/splat_cpu.cpp, ``project_backward``) plus the
spherical-harmonics colour, which the ``cuda`` projection evaluates in its kernel: the forward
quantities are recomputed from the inputs (cheaper than storing them), then each step of the
forward is walked back:

    t = Rv m + tv, dist = |t|, n = t / dist            (camera frame)
    L = Rv R(q) S, M2 = T2(n, dist) L                   (T2: tangent basis / dist, or the pinhole Jacobian)
    Σ = M2 M2ᵀ + eps I, Q = Σ⁻¹                         (dL/dΣ = −Q Gm Q)
    rgb = max(SH(Rvᵀ n) + 0.5, 0)                       (SH colours)

One program per BLOCK Gaussians; the view matrix's gradient is summed per program and the
programs' sums added by one ``sum``. Rows the forward did not keep (``visible`` false) get
zero. The torch reference (``project(..., keep=visible)`` under autograd) is what the tests
compare it with; it replaced ~760 element-wise launches per backward (issue 35).
"""

from __future__ import annotations

import math

import torch

from . import compile_ahead
from .devices import cdiv
from .project import PACK
from .project_triton import BLOCK, _camera_vector, triton

if triton is not None:
    import triton.language as tl

    from .project_triton import _rotation, _sh_channel, _tangent_basis, _unit_quat, _view_rotation

    _PACKB = tl.constexpr(PACK)
    _C1 = tl.constexpr(0.4886025119029199)
    _NC1 = tl.constexpr(-0.4886025119029199)  # a negated constexpr is not a constexpr in the interpreter
    _C2_0 = tl.constexpr(1.0925484305920792)
    _C2_1 = tl.constexpr(-1.0925484305920792)
    _C2_2 = tl.constexpr(0.31539156525252005)
    _C2_3 = tl.constexpr(-1.0925484305920792)
    _C2_4 = tl.constexpr(0.5462742152960396)
    _C3_0 = tl.constexpr(-0.5900435899266435)
    _C3_1 = tl.constexpr(2.890611442640554)
    _C3_2 = tl.constexpr(-0.4570457994644658)
    _C3_3 = tl.constexpr(0.3731763325901154)
    _C3_4 = tl.constexpr(-0.4570457994644658)
    _C3_5 = tl.constexpr(1.445305721320277)
    _C3_6 = tl.constexpr(-0.5900435899266435)

    @triton.jit
    def _sh_channel_backward(colors, gcolors, i, ok, x, y, z, g, ch: tl.constexpr, DEG: tl.constexpr,
                             K: tl.constexpr):
        """One colour channel's SH coefficients' gradient (stored) given the channel's gradient g,
        and the gradient of the (unit) direction x, y, z, returned."""
        base = colors + i * (K * 3) + ch
        gbase = gcolors + i * (K * 3) + ch
        # products are written tensor first: in the interpreter, constexpr * tensor stays a constexpr
        tl.store(gbase, g * 0.28209479177387814, mask=ok)
        gx = g * 0
        gy = g * 0
        gz = g * 0
        if DEG > 0:
            c1 = tl.load(base + 3, mask=ok, other=0)
            c2 = tl.load(base + 6, mask=ok, other=0)
            c3 = tl.load(base + 9, mask=ok, other=0)
            tl.store(gbase + 3, g * y * _NC1, mask=ok)
            tl.store(gbase + 6, g * z * _C1, mask=ok)
            tl.store(gbase + 9, g * x * _NC1, mask=ok)
            dx = c3 * _NC1
            dy = c1 * _NC1
            dz = c2 * _C1
            if DEG > 1:
                xx = x * x
                yy = y * y
                zz = z * z
                c4 = tl.load(base + 12, mask=ok, other=0)
                c5 = tl.load(base + 15, mask=ok, other=0)
                c6 = tl.load(base + 18, mask=ok, other=0)
                c7 = tl.load(base + 21, mask=ok, other=0)
                c8 = tl.load(base + 24, mask=ok, other=0)
                tl.store(gbase + 12, g * (x * y) * _C2_0, mask=ok)
                tl.store(gbase + 15, g * (y * z) * _C2_1, mask=ok)
                tl.store(gbase + 18, g * (2.0 * zz - xx - yy) * _C2_2, mask=ok)
                tl.store(gbase + 21, g * (x * z) * _C2_3, mask=ok)
                tl.store(gbase + 24, g * (xx - yy) * _C2_4, mask=ok)
                dx += y * c4 * _C2_0 - x * c6 * (2.0 * _C2_2) + z * c7 * _C2_3 + x * c8 * (2.0 * _C2_4)
                dy += x * c4 * _C2_0 + z * c5 * _C2_1 - y * c6 * (2.0 * _C2_2) - y * c8 * (2.0 * _C2_4)
                dz += y * c5 * _C2_1 + z * c6 * (4.0 * _C2_2) + x * c7 * _C2_3
                if DEG > 2:
                    c9 = tl.load(base + 27, mask=ok, other=0)
                    c10 = tl.load(base + 30, mask=ok, other=0)
                    c11 = tl.load(base + 33, mask=ok, other=0)
                    c12 = tl.load(base + 36, mask=ok, other=0)
                    c13 = tl.load(base + 39, mask=ok, other=0)
                    c14 = tl.load(base + 42, mask=ok, other=0)
                    c15 = tl.load(base + 45, mask=ok, other=0)
                    tl.store(gbase + 27, g * y * (3 * xx - yy) * _C3_0, mask=ok)
                    tl.store(gbase + 30, g * (x * y) * z * _C3_1, mask=ok)
                    tl.store(gbase + 33, g * y * (4 * zz - xx - yy) * _C3_2, mask=ok)
                    tl.store(gbase + 36, g * z * (2 * zz - 3 * xx - 3 * yy) * _C3_3, mask=ok)
                    tl.store(gbase + 39, g * x * (4 * zz - xx - yy) * _C3_4, mask=ok)
                    tl.store(gbase + 42, g * z * (xx - yy) * _C3_5, mask=ok)
                    tl.store(gbase + 45, g * x * (xx - 3 * yy) * _C3_6, mask=ok)
                    dx += (x * y * c9 * (6.0 * _C3_0) + y * z * c10 * _C3_1 - x * y * c11 * (2.0 * _C3_2)
                           - x * z * c12 * (6.0 * _C3_3) + (4 * zz - 3 * xx - yy) * c13 * _C3_4
                           + x * z * c14 * (2.0 * _C3_5) + (3 * xx - 3 * yy) * c15 * _C3_6)
                    dy += ((3 * xx - 3 * yy) * c9 * _C3_0 + x * z * c10 * _C3_1 + (4 * zz - xx - 3 * yy) * c11 * _C3_2
                           - y * z * c12 * (6.0 * _C3_3) - x * y * c13 * (2.0 * _C3_4) - y * z * c14 * (2.0 * _C3_5)
                           - x * y * c15 * (6.0 * _C3_6))
                    dz += (x * y * c10 * _C3_1 + y * z * c11 * (8.0 * _C3_2) + (6 * zz - 3 * xx - 3 * yy) * c12 * _C3_3
                           + x * z * c13 * (8.0 * _C3_4) + (xx - yy) * c14 * _C3_5)
            gx = g * dx
            gy = g * dy
            gz = g * dz
        return gx, gy, gz

    # N not specialised, as the forward's: the SH 3 gradient takes 8.2 s to compile on sm_90
    @triton.jit(do_not_specialize=["N"])
    def _project_bwd(means, quats, scales, colors, viewmat, cam, visible, gP,
                     g_means, g_quats, g_scales, g_opac, g_colors, g_m2d, g_view, N,
                     EQUIRECT: tl.constexpr, SH_DEGREE: tl.constexpr, K: tl.constexpr, BLOCK: tl.constexpr,
                     VIEW_GRAD: tl.constexpr):
        pid = tl.program_id(0)
        i = pid * BLOCK + tl.arange(0, BLOCK)
        ok_i = i < N
        valid = tl.load(visible + i, mask=ok_i, other=0) != 0
        sx = tl.load(cam + 0)
        sy = tl.load(cam + 1)
        limx = tl.load(cam + 4)
        limy = tl.load(cam + 5)
        eps2d = tl.load(cam + 6)
        mx = tl.load(means + i * 3, mask=ok_i, other=0)
        my = tl.load(means + i * 3 + 1, mask=ok_i, other=0)
        mz = tl.load(means + i * 3 + 2, mask=ok_i, other=0)
        v00, v01, v02, v10, v11, v12, v20, v21, v22 = _view_rotation(viewmat)
        # stand-ins on the rows not kept (finite everywhere; their gradients are stored as zero)
        mx = tl.where(valid, mx, 0.0)
        my = tl.where(valid, my, 0.0)
        mz = tl.where(valid, mz, 0.0)
        tx = mx * v00 + my * v01 + mz * v02 + tl.load(viewmat + 3)
        ty = mx * v10 + my * v11 + mz * v12 + tl.load(viewmat + 7)
        tz = mx * v20 + my * v21 + mz * v22 + tl.load(viewmat + 11)
        tx = tl.where(valid, tx, 0.0)
        ty = tl.where(valid, ty, 0.0)
        tz = tl.where(valid, tz, 1.0)
        s0 = tl.where(valid, tl.load(scales + i * 3, mask=ok_i, other=0), 1e-2)
        s1 = tl.where(valid, tl.load(scales + i * 3 + 1, mask=ok_i, other=0), 1e-2)
        s2 = tl.where(valid, tl.load(scales + i * 3 + 2, mask=ok_i, other=0), 1e-2)
        rw = tl.where(valid, tl.load(quats + i * 4, mask=ok_i, other=0), 1.0)
        rx = tl.where(valid, tl.load(quats + i * 4 + 1, mask=ok_i, other=0), 0.0)
        ry = tl.where(valid, tl.load(quats + i * 4 + 2, mask=ok_i, other=0), 0.0)
        rz = tl.where(valid, tl.load(quats + i * 4 + 3, mask=ok_i, other=0), 0.0)
        dist = tl.sqrt(tl.maximum(tx * tx + ty * ty + tz * tz, 1e-30))
        nx = tx / dist
        ny = ty / dist
        nz = tz / dist
        n2q = rw * rw + rx * rx + ry * ry + rz * rz
        qw, qx, qy, qz, qinv = _unit_quat(rw, rx, ry, rz)
        q00, q01, q02, q10, q11, q12, q20, q21, q22 = _rotation(qw, qx, qy, qz)
        # M = R(q) S and L = Rv M
        M00 = q00 * s0
        M01 = q01 * s1
        M02 = q02 * s2
        M10 = q10 * s0
        M11 = q11 * s1
        M12 = q12 * s2
        M20 = q20 * s0
        M21 = q21 * s1
        M22 = q22 * s2
        L00 = v00 * M00 + v01 * M10 + v02 * M20
        L01 = v00 * M01 + v01 * M11 + v02 * M21
        L02 = v00 * M02 + v01 * M12 + v02 * M22
        L10 = v10 * M00 + v11 * M10 + v12 * M20
        L11 = v10 * M01 + v11 * M11 + v12 * M21
        L12 = v10 * M02 + v11 * M12 + v12 * M22
        L20 = v20 * M00 + v21 * M10 + v22 * M20
        L21 = v20 * M01 + v21 * M11 + v22 * M21
        L22 = v20 * M02 + v21 * M12 + v22 * M22
        if EQUIRECT:
            sign, a, e10, e11, e12, e20, e21, e22 = _tangent_basis(nx, ny, nz)
            k1 = sx / dist
            k2 = sy / dist
            T00 = e10 * k1
            T01 = e11 * k1
            T02 = e12 * k1
            T10 = e20 * k2
            T11 = e21 * k2
            T12 = e22 * k2
        else:
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
        p0 = T00 * L00 + T01 * L10 + T02 * L20
        p1 = T00 * L01 + T01 * L11 + T02 * L21
        p2 = T00 * L02 + T01 * L12 + T02 * L22
        r0 = T10 * L00 + T11 * L10 + T12 * L20
        r1 = T10 * L01 + T11 * L11 + T12 * L21
        r2 = T10 * L02 + T11 * L12 + T12 * L22
        a0 = p0 * p0 + p1 * p1 + p2 * p2
        c0 = r0 * r0 + r1 * r1 + r2 * r2
        bb = p0 * r0 + p1 * r1 + p2 * r2
        m01 = p0 * r1 - p1 * r0
        m02 = p0 * r2 - p2 * r0
        m12 = p1 * r2 - p2 * r1
        det = m01 * m01 + m02 * m02 + m12 * m12 + eps2d * (a0 + c0) + eps2d * eps2d
        det = tl.where(valid, det, 1.0)
        Q0 = (c0 + eps2d) / det
        Q1 = -bb / det
        Q2 = (a0 + eps2d) / det

        G = gP + i * _PACKB
        G0 = tl.load(G + 0, mask=ok_i, other=0)
        G1 = tl.load(G + 1, mask=ok_i, other=0)
        G2 = tl.load(G + 2, mask=ok_i, other=0)
        G3 = tl.load(G + 3, mask=ok_i, other=0)
        G4 = tl.load(G + 4, mask=ok_i, other=0)
        G5 = tl.load(G + 5, mask=ok_i, other=0)
        G9 = tl.load(G + 9, mask=ok_i, other=0)
        G10 = tl.load(G + 10, mask=ok_i, other=0)
        # conic -> covariance: dL/dΣ = −Q Gm Q, Gm = [[g00, g01/2], [g01/2, g11]]
        g00 = tl.load(G + 11, mask=ok_i, other=0)
        g01 = 0.5 * tl.load(G + 12, mask=ok_i, other=0)
        g11 = tl.load(G + 13, mask=ok_i, other=0)
        x00 = g00 * Q0 + g01 * Q1
        x01 = g00 * Q1 + g01 * Q2
        x10 = g01 * Q0 + g11 * Q1
        x11 = g01 * Q1 + g11 * Q2
        gA = -(Q0 * x00 + Q1 * x10)
        gB = -2.0 * (Q0 * x01 + Q1 * x11)
        gC = -(Q1 * x01 + Q2 * x11)
        # Σ from the rows p, r of M2
        gp0 = 2 * gA * p0 + gB * r0
        gp1 = 2 * gA * p1 + gB * r1
        gp2 = 2 * gA * p2 + gB * r2
        gr0 = 2 * gC * r0 + gB * p0
        gr1 = 2 * gC * r1 + gB * p1
        gr2 = 2 * gC * r2 + gB * p2
        # M2 = T2 L: the rows of T2 and L
        gT00 = L00 * gp0 + L01 * gp1 + L02 * gp2
        gT01 = L10 * gp0 + L11 * gp1 + L12 * gp2
        gT02 = L20 * gp0 + L21 * gp1 + L22 * gp2
        gT10 = L00 * gr0 + L01 * gr1 + L02 * gr2
        gT11 = L10 * gr0 + L11 * gr1 + L12 * gr2
        gT12 = L20 * gr0 + L21 * gr1 + L22 * gr2
        gL00 = T00 * gp0 + T10 * gr0
        gL01 = T00 * gp1 + T10 * gr1
        gL02 = T00 * gp2 + T10 * gr2
        gL10 = T01 * gp0 + T11 * gr0
        gL11 = T01 * gp1 + T11 * gr1
        gL12 = T01 * gp2 + T11 * gr2
        gL20 = T02 * gp0 + T12 * gr0
        gL21 = T02 * gp1 + T12 * gr1
        gL22 = T02 * gp2 + T12 * gr2

        # colour: RGB as is; SH through the coefficients and the world direction w = Rvᵀ n
        gcr = tl.load(G + 15, mask=ok_i, other=0)
        gcg = tl.load(G + 16, mask=ok_i, other=0)
        gcb = tl.load(G + 17, mask=ok_i, other=0)
        gnx = nx * 0
        gny = nx * 0
        gnz = nx * 0
        gv00 = nx * 0
        gv01 = nx * 0
        gv02 = nx * 0
        gv10 = nx * 0
        gv11 = nx * 0
        gv12 = nx * 0
        gv20 = nx * 0
        gv21 = nx * 0
        gv22 = nx * 0
        if SH_DEGREE < 0:
            tl.store(g_colors + i * 3, tl.where(valid, gcr, 0.0), mask=ok_i)
            tl.store(g_colors + i * 3 + 1, tl.where(valid, gcg, 0.0), mask=ok_i)
            tl.store(g_colors + i * 3 + 2, tl.where(valid, gcb, 0.0), mask=ok_i)
        else:
            wx = nx * v00 + ny * v10 + nz * v20
            wy = nx * v01 + ny * v11 + nz * v21
            wz = nx * v02 + ny * v12 + nz * v22
            # the clamp at 0 (torch.clamp_min passes the gradient where its input is >= 0)
            gcr = tl.where(valid & (_sh_channel(colors, i, ok_i, wx, wy, wz, 0, SH_DEGREE, K) + 0.5 >= 0), gcr, 0.0)
            gcg = tl.where(valid & (_sh_channel(colors, i, ok_i, wx, wy, wz, 1, SH_DEGREE, K) + 0.5 >= 0), gcg, 0.0)
            gcb = tl.where(valid & (_sh_channel(colors, i, ok_i, wx, wy, wz, 2, SH_DEGREE, K) + 0.5 >= 0), gcb, 0.0)
            rn = 1.0 / tl.sqrt(tl.maximum(wx * wx + wy * wy + wz * wz, 1e-30))
            ux = wx * rn
            uy = wy * rn
            uz = wz * rn
            dxr, dyr, dzr = _sh_channel_backward(colors, g_colors, i, ok_i, ux, uy, uz, gcr, 0, SH_DEGREE, K)
            dxg, dyg, dzg = _sh_channel_backward(colors, g_colors, i, ok_i, ux, uy, uz, gcg, 1, SH_DEGREE, K)
            dxb, dyb, dzb = _sh_channel_backward(colors, g_colors, i, ok_i, ux, uy, uz, gcb, 2, SH_DEGREE, K)
            gux = dxr + dxg + dxb
            guy = dyr + dyg + dyb
            guz = dzr + dzg + dzb
            # through the normalisation u = w / |w|
            ug = ux * gux + uy * guy + uz * guz
            gwx = (gux - ux * ug) * rn
            gwy = (guy - uy * ug) * rn
            gwz = (guz - uz * ug) * rn
            gnx = v00 * gwx + v01 * gwy + v02 * gwz
            gny = v10 * gwx + v11 * gwy + v12 * gwz
            gnz = v20 * gwx + v21 * gwy + v22 * gwz
            gv00 = nx * gwx
            gv01 = nx * gwy
            gv02 = nx * gwz
            gv10 = ny * gwx
            gv11 = ny * gwy
            gv12 = ny * gwz
            gv20 = nz * gwx
            gv21 = nz * gwy
            gv22 = nz * gwz

        # the centre: gdist and gn, then t
        gdist = tl.load(G + 18, mask=ok_i, other=0)
        gtx = nx * 0
        gty = nx * 0
        gtz = nx * 0
        if EQUIRECT:
            # packed a1 = e1 sx, a2 = e2 sy, n; T2 rows = e1 k1, e2 k2 (k = s / dist)
            ge10 = gT00 * k1 + sx * G0
            ge11 = gT01 * k1 + sx * G1
            ge12 = gT02 * k1 + sx * G2
            ge20 = gT10 * k2 + sy * G3
            ge21 = gT11 * k2 + sy * G4
            ge22 = gT12 * k2 + sy * G5
            gdist -= (gT00 * T00 + gT01 * T01 + gT02 * T02 + gT10 * T10 + gT11 * T11 + gT12 * T12) / dist
            a2 = a * a
            gnx += tl.load(G + 6, mask=ok_i, other=0) + ge10 * sign * 2 * nx * a + ge11 * sign * ny * a \
                - ge12 * sign + ge20 * ny * a
            gny += tl.load(G + 7, mask=ok_i, other=0) + ge11 * sign * nx * a + ge20 * nx * a \
                + ge21 * 2 * ny * a - ge22
            gnz += tl.load(G + 8, mask=ok_i, other=0) + ge10 * sign * nx * nx * a2 + ge11 * sign * nx * ny * a2 \
                + ge20 * nx * ny * a2 + ge21 * ny * ny * a2
            # means2d: uvc = rot (means2d − its value), rot from (e1, e2) onto (east, south)
            h = tl.sqrt(nx * nx + nz * nz)
            hok = h > 1e-12
            hs = tl.where(hok, h, 1.0)
            ex = tl.where(hok, nz / hs, 1.0)
            ez = tl.where(hok, -nx / hs, 0.0)
            # south = n × east (east has no y)
            sx_ = ny * ez
            sy_ = nz * ex - nx * ez
            sz_ = -ny * ex
            rot00 = e10 * ex + e12 * ez
            rot01 = e10 * sx_ + e11 * sy_ + e12 * sz_
            rot10 = e20 * ex + e22 * ez
            rot11 = e20 * sx_ + e21 * sy_ + e22 * sz_
            gm2x = rot00 * G9 + rot10 * G10
            gm2y = rot01 * G9 + rot11 * G10
        else:
            zz2 = tz * tz
            gz = -gT00 * sx / zz2 + gT02 * sx * jx / zz2 - gT11 * sy / zz2 + gT12 * sy * jy / zz2
            gjx = -gT02 * sx / tz
            gjy = -gT12 * sy / tz
            gmx = sx * G9 + tl.where(jx == pmx, gjx, 0.0)
            gmy = sy * G10 + tl.where(jy == pmy, gjy, 0.0)
            gtx += gmx / tz
            gty += gmy / tz
            gtz += gz - (gmx * pmx + gmy * pmy) / tz
            gm2x = G9
            gm2y = G10
        ndg = nx * gnx + ny * gny + nz * gnz
        gtx += (gnx - nx * ndg) / dist + nx * gdist
        gty += (gny - ny * ndg) / dist + ny * gdist
        gtz += (gnz - nz * ndg) / dist + nz * gdist

        # L = Rv M: gM = Rvᵀ gL, gRv += gL Mᵀ
        gM00 = v00 * gL00 + v10 * gL10 + v20 * gL20
        gM01 = v00 * gL01 + v10 * gL11 + v20 * gL21
        gM02 = v00 * gL02 + v10 * gL12 + v20 * gL22
        gM10 = v01 * gL00 + v11 * gL10 + v21 * gL20
        gM11 = v01 * gL01 + v11 * gL11 + v21 * gL21
        gM12 = v01 * gL02 + v11 * gL12 + v21 * gL22
        gM20 = v02 * gL00 + v12 * gL10 + v22 * gL20
        gM21 = v02 * gL01 + v12 * gL11 + v22 * gL21
        gM22 = v02 * gL02 + v12 * gL12 + v22 * gL22
        gv00 += gL00 * M00 + gL01 * M01 + gL02 * M02
        gv01 += gL00 * M10 + gL01 * M11 + gL02 * M12
        gv02 += gL00 * M20 + gL01 * M21 + gL02 * M22
        gv10 += gL10 * M00 + gL11 * M01 + gL12 * M02
        gv11 += gL10 * M10 + gL11 * M11 + gL12 * M12
        gv12 += gL10 * M20 + gL11 * M21 + gL12 * M22
        gv20 += gL20 * M00 + gL21 * M01 + gL22 * M02
        gv21 += gL20 * M10 + gL21 * M11 + gL22 * M12
        gv22 += gL20 * M20 + gL21 * M21 + gL22 * M22
        # M = R S
        gs0 = q00 * gM00 + q10 * gM10 + q20 * gM20
        gs1 = q01 * gM01 + q11 * gM11 + q21 * gM21
        gs2 = q02 * gM02 + q12 * gM12 + q22 * gM22
        gR0 = gM00 * s0
        gR1 = gM01 * s1
        gR2 = gM02 * s2
        gR3 = gM10 * s0
        gR4 = gM11 * s1
        gR5 = gM12 * s2
        gR6 = gM20 * s0
        gR7 = gM21 * s1
        gR8 = gM22 * s2
        gqw = 2 * (-qz * gR1 + qy * gR2 + qz * gR3 - qx * gR5 - qy * gR6 + qx * gR7)
        gqx = 2 * (qy * gR1 + qz * gR2 + qy * gR3 - 2 * qx * gR4 - qw * gR5 + qz * gR6 + qw * gR7 - 2 * qx * gR8)
        gqy = 2 * (-2 * qy * gR0 + qx * gR1 + qw * gR2 + qx * gR3 + qz * gR5 - qw * gR6 + qz * gR7 - 2 * qy * gR8)
        gqz = 2 * (-2 * qz * gR0 - qw * gR1 + qx * gR2 + qw * gR3 - 2 * qz * gR4 + qy * gR5 + qx * gR6 + qy * gR7)
        # q / |q| (the clamp below 1e-24 passes no gradient through the norm)
        dot = tl.where(n2q >= 1e-24, gqw * qw + gqx * qx + gqy * qy + gqz * qz, 0.0)
        gqw = (gqw - qw * dot) * qinv
        gqx = (gqx - qx * dot) * qinv
        gqy = (gqy - qy * dot) * qinv
        gqz = (gqz - qz * dot) * qinv
        # t = Rv m + tv
        gmx_ = v00 * gtx + v10 * gty + v20 * gtz
        gmy_ = v01 * gtx + v11 * gty + v21 * gtz
        gmz_ = v02 * gtx + v12 * gty + v22 * gtz
        gv00 += gtx * mx
        gv01 += gtx * my
        gv02 += gtx * mz
        gv10 += gty * mx
        gv11 += gty * my
        gv12 += gty * mz
        gv20 += gtz * mx
        gv21 += gtz * my
        gv22 += gtz * mz

        zero = gtx * 0
        tl.store(g_means + i * 3, tl.where(valid, gmx_, zero), mask=ok_i)
        tl.store(g_means + i * 3 + 1, tl.where(valid, gmy_, zero), mask=ok_i)
        tl.store(g_means + i * 3 + 2, tl.where(valid, gmz_, zero), mask=ok_i)
        tl.store(g_quats + i * 4, tl.where(valid, gqw, zero), mask=ok_i)
        tl.store(g_quats + i * 4 + 1, tl.where(valid, gqx, zero), mask=ok_i)
        tl.store(g_quats + i * 4 + 2, tl.where(valid, gqy, zero), mask=ok_i)
        tl.store(g_quats + i * 4 + 3, tl.where(valid, gqz, zero), mask=ok_i)
        tl.store(g_scales + i * 3, tl.where(valid, gs0, zero), mask=ok_i)
        tl.store(g_scales + i * 3 + 1, tl.where(valid, gs1, zero), mask=ok_i)
        tl.store(g_scales + i * 3 + 2, tl.where(valid, gs2, zero), mask=ok_i)
        tl.store(g_opac + i, tl.where(valid, tl.load(G + 14, mask=ok_i, other=0), zero), mask=ok_i)
        tl.store(g_m2d + i * 2, tl.where(valid, gm2x, zero), mask=ok_i)
        tl.store(g_m2d + i * 2 + 1, tl.where(valid, gm2y, zero), mask=ok_i)
        if VIEW_GRAD:  # the view matrix: this program's sums (rows 0-2 of the 4x4; row 3 stays zero)
            gv = g_view + pid * 16
            tl.store(gv + 0, tl.sum(tl.where(valid, gv00, zero), axis=0))
            tl.store(gv + 1, tl.sum(tl.where(valid, gv01, zero), axis=0))
            tl.store(gv + 2, tl.sum(tl.where(valid, gv02, zero), axis=0))
            tl.store(gv + 3, tl.sum(tl.where(valid, gtx, zero), axis=0))
            tl.store(gv + 4, tl.sum(tl.where(valid, gv10, zero), axis=0))
            tl.store(gv + 5, tl.sum(tl.where(valid, gv11, zero), axis=0))
            tl.store(gv + 6, tl.sum(tl.where(valid, gv12, zero), axis=0))
            tl.store(gv + 7, tl.sum(tl.where(valid, gty, zero), axis=0))
            tl.store(gv + 8, tl.sum(tl.where(valid, gv20, zero), axis=0))
            tl.store(gv + 9, tl.sum(tl.where(valid, gv21, zero), axis=0))
            tl.store(gv + 10, tl.sum(tl.where(valid, gv22, zero), axis=0))
            tl.store(gv + 11, tl.sum(tl.where(valid, gtz, zero), axis=0))
            tl.store(gv + 12, tl.sum(zero, axis=0))
            tl.store(gv + 13, tl.sum(zero, axis=0))
            tl.store(gv + 14, tl.sum(zero, axis=0))
            tl.store(gv + 15, tl.sum(zero, axis=0))

def backward_launch(means, quats, scales, colors, viewmat, camvec, visible, gP, outs, equirect, sh_degree, K):
    """(kernel, grid, args, options) of the projection's backward, for the launch and the compile check;
    the last of `outs` (the view matrix's per-program sums) None: no gradient for the view matrix."""
    N = means.shape[0]
    grid = (max(1, cdiv(N, BLOCK)),)
    *grads, g_view = outs
    view_grad = g_view is not None
    g_view = grads[0] if g_view is None else g_view  # any pointer: never written without the flag
    return (_project_bwd, grid, (means, quats, scales, colors, viewmat, camvec, visible, gP, *grads, g_view, N),
            dict(EQUIRECT=bool(equirect), SH_DEGREE=int(sh_degree), K=int(K), BLOCK=BLOCK, num_warps=2,
                 VIEW_GRAD=view_grad))


def project_backward(means, quats, scales, colors, viewmat, visible, g_packed, camera, eps2d, near, sh_degree,
                     view_grad: bool = True):
    """Gradients (means, quats, scales, opacities, colours, viewmat, means2d) of the projection
    from its packed rows' gradient: one kernel and one sum (the view matrix's; with `view_grad`
    False neither that sum nor its buffer, and the view matrix's gradient is None), no host sync."""
    from .cameras import EquirectCamera

    dtype, device = means.dtype, means.device
    N = means.shape[0]
    K = colors.shape[1] if colors.dim() == 3 else 1
    deg = -1 if colors.dim() == 2 else int(sh_degree)
    nprog = max(1, cdiv(N, BLOCK))
    # the gradients are views of one buffer: one allocation, not six (autograd keeps them as they
    # are: each view is contiguous with its parameter's layout). Each starts 16-byte aligned, as
    # a buffer of its own would: Triton specialises a launch on its pointers' alignment
    shapes = (means.shape, quats.shape, scales.shape, (N,), colors.shape, (N, 2))
    sizes = [math.prod(shape) for shape in shapes]
    padded = [cdiv(n, 4) * 4 for n in sizes]
    buffer = torch.empty(sum(padded), dtype=dtype, device=device)
    g_means, g_quats, g_scales, g_opac, g_colors, g_m2d = (
        flat[:n].view(shape) for flat, n, shape in zip(buffer.split(padded), sizes, shapes))
    if deg >= 0 and K > (deg + 1) ** 2:
        g_colors.zero_()  # SH coefficients past the degree in use get no gradient: zeros, written by nobody
    g_view = torch.empty(nprog, 16, dtype=dtype, device=device) if view_grad else None
    if N:
        camvec = _camera_vector(camera, eps2d, near, dtype, device)
        kernel, grid, args, options = backward_launch(
            means.contiguous(), quats.contiguous(), scales.contiguous(), colors.contiguous(), viewmat.contiguous(),
            camvec, visible, g_packed.contiguous(), (g_means, g_quats, g_scales, g_opac, g_colors, g_m2d, g_view),
            isinstance(camera, EquirectCamera), deg, K)
        compile_ahead.launch(kernel, grid, args, options)  # with the later SH degrees' compiles, if asked
        g_viewmat = g_view.sum(0).reshape(4, 4) if view_grad else None
    else:
        g_viewmat = torch.zeros(4, 4, dtype=dtype, device=device) if view_grad else None
    return g_means, g_quats, g_scales, g_opac, g_colors, g_viewmat, g_m2d
