"""A perspective depth model on the six cube faces of a panorama, faces aligned and stitched.

Faces (OpenCV axes, each looks along its own +z): front +z, right +x, back -z,
left -x, up -y, down +y, the order of splatting.cubemap_faces. A field of
view above 90° makes neighbouring faces overlap; the overlaps fix each face's
own scale (and shift) relative to the front face:

- a perspective model measures depth along its optical axis, z = r cos(a)
  (r the distance along the ray, a the angle between the ray and the face's
  axis), and disparity 1/z;
- face i's prediction p_i is true up to its own affine map (metric: scale
  only), z_i = s_i p_i + t_i, or 1/z_i = s_i p_i + t_i for disparity;
- in an overlap both faces see the same ray, so
  (s_i p_i + t_i)/cos(a_i) = (s_j p_j + t_j)/cos(a_j) (depth), or
  cos(a_i)(s_i p_i + t_i) = cos(a_j)(s_j p_j + t_j) (disparity):
  linear in the unknowns, solved by least squares with s_front = 1. Because
  a_i and a_j differ across an overlap, even the front face's shift is
  determined; the stitched map is then the ray quantity up to one scale.

The stitched value of a pixel is the cos^8-weighted mean of the aligned faces
that see it (the face centres are the most reliable).
"""

from __future__ import annotations

import cv2
import numpy as np

from panogeom.equirect import angles_to_pixel, dirs_to_angles, ray_directions
from splatting.cameras import CUBEMAP_FACE_AXES, CUBEMAP_FACE_NAMES

# The same six faces as the cubemap baseline renders (front, right, back, left, up, down).
FACE_NAMES = CUBEMAP_FACE_NAMES
FACE_AXES = CUBEMAP_FACE_AXES


def face_rotation(name: str) -> np.ndarray:
    """3x3 matrix whose rows are the face axes: d_face = M @ d_cam, d_cam = M.T @ d_face."""
    return np.asarray(FACE_AXES[name], dtype=np.float64)


def focal(size: int, fov_deg: float) -> float:
    return (size / 2.0) / np.tan(np.radians(fov_deg) / 2.0)


def face_dirs(size: int, fov_deg: float) -> np.ndarray:
    """[S,S,3] face-frame ray directions (z = 1) of the face pixel centres."""
    f = focal(size, fov_deg)
    c = (np.arange(size) + 0.5 - size / 2.0) / f
    x, y = np.meshgrid(c, c)
    return np.stack([x, y, np.ones_like(x)], -1)


def face_cos(size: int, fov_deg: float) -> np.ndarray:
    """[S,S] cosine between each face pixel's ray and the face axis."""
    d = face_dirs(size, fov_deg)
    return (1.0 / np.linalg.norm(d, axis=-1)).astype(np.float32)


def sample_face(equirect: np.ndarray, name: str, size: int, fov_deg: float) -> np.ndarray:
    """Render one cube face [S,S,C] of an equirectangular image by bilinear lookup (longitude wraps)."""
    h, w = equirect.shape[:2]
    d = face_dirs(size, fov_deg) @ face_rotation(name)  # rows: d_cam = M.T d_face
    phi, theta = dirs_to_angles(d)
    col, row = angles_to_pixel(phi, theta, h, w)
    pad = 2
    padded = np.concatenate([equirect[:, -pad:], equirect, equirect[:, :pad]], axis=1)
    out = cv2.remap(
        np.ascontiguousarray(padded, dtype=np.float32),
        (col + pad).astype(np.float32),
        row.astype(np.float32),
        interpolation=cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    )
    return out.reshape(size, size, -1) if equirect.ndim == 3 else out


def project_faces(face_maps: np.ndarray, fov_deg: float, out_hw: tuple[int, int]):
    """Look every equirectangular pixel up in every face.

    face_maps [6,S,S]; returns (values [6,H,W] NaN where a face does not see
    the pixel, cos [6,H,W] the angle cosine to each face's axis).
    """
    h, w = out_hw
    size = face_maps.shape[-1]
    f = focal(size, fov_deg)
    d = ray_directions(h, w)
    vals = np.full((6, h, w), np.nan, np.float32)
    coss = np.zeros((6, h, w), np.float32)
    for i, name in enumerate(FACE_NAMES):
        df = d @ face_rotation(name).T  # d_face = M d_cam
        z = df[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = f * df[..., 0] / z + size / 2.0 - 0.5
            v = f * df[..., 1] / z + size / 2.0 - 0.5
        inside = (z > 1e-6) & (u >= -0.5) & (u <= size - 0.5) & (v >= -0.5) & (v <= size - 0.5)
        u = np.where(inside, u, -10).astype(np.float32)
        v = np.where(inside, v, -10).astype(np.float32)
        s = cv2.remap(
            face_maps[i].astype(np.float32), u, v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
        )
        vals[i] = np.where(inside, s, np.nan)
        coss[i] = np.where(inside, z, 0.0)
    return vals, coss


def align_faces(
    vals: np.ndarray, coss: np.ndarray, kind: str, max_rows: int = 200_000, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Per-face (scale, shift) [6] each, front face scale 1, from the overlaps (module docstring)."""
    axis_factor = coss if kind == "disparity" else 1.0 / np.maximum(coss, 1e-6)
    valid = np.isfinite(vals)
    rows_i, rows_j, pix = [], [], []
    flat_valid = valid.reshape(6, -1)
    for i in range(6):
        for j in range(i + 1, 6):
            both = np.flatnonzero(flat_valid[i] & flat_valid[j])
            if len(both):
                rows_i.append(np.full(len(both), i))
                rows_j.append(np.full(len(both), j))
                pix.append(both)
    if not pix:
        return np.ones(6), np.zeros(6)
    ri, rj, px = np.concatenate(rows_i), np.concatenate(rows_j), np.concatenate(pix)
    if len(px) > max_rows:
        sel = np.random.default_rng(seed).choice(len(px), max_rows, replace=False)
        ri, rj, px = ri[sel], rj[sel], px[sel]
    v = vals.reshape(6, -1)
    a = np.broadcast_to(axis_factor, vals.shape).reshape(6, -1)
    vi, vj, ai, aj = v[ri, px], v[rj, px], a[ri, px], a[rj, px]
    affine = kind != "metric"
    n_unk = 12 if affine else 6
    # Row: a_i (s_i v_i + t_i) - a_j (s_j v_j + t_j) = 0, scaled to a relative residual.
    w = 1.0 / np.maximum(np.abs(ai * vi) + np.abs(aj * vj), 1e-9)
    A = np.zeros((len(px), n_unk))
    rows = np.arange(len(px))
    A[rows, ri] = ai * vi * w
    A[rows, rj] = -aj * vj * w
    if affine:
        A[rows, 6 + ri] = ai * w
        A[rows, 6 + rj] = -aj * w
    keep = np.ones(len(px), bool)
    x = np.zeros(n_unk)
    for _ in range(3):  # least squares, then drop gross disagreements (occlusion edges, model seams)
        b = -A[keep, 0]  # s_front = 1 moves to the right-hand side
        sol, *_ = np.linalg.lstsq(A[keep, 1:], b, rcond=None)
        x = np.concatenate([[1.0], sol])
        res = np.abs(A @ x)
        mad = np.median(res[keep]) + 1e-12
        new_keep = res < max(6 * mad, 1e-6)
        if new_keep.sum() < n_unk or np.array_equal(new_keep, keep):
            break
        keep = new_keep
    scales = x[:6]
    shifts = x[6:] if affine else np.zeros(6)
    if not (np.all(np.isfinite(x)) and np.all(scales > 0)):
        # The faces contradict each other (a model that does not generalise to these views):
        # a sign flip would invalidate whole faces, so keep them as predicted and let align fit.
        return np.ones(6), np.zeros(6)
    return scales, shifts


def stitch(
    face_maps: np.ndarray,
    kind: str,
    fov_deg: float,
    out_hw: tuple[int, int],
    axis: str = "z",
    align: bool = True,
) -> tuple[np.ndarray, dict]:
    """Six face predictions [6,S,S] -> an equirectangular map of the ray quantity (distance or 1/distance)."""
    vals, coss = project_faces(face_maps, fov_deg, out_hw)
    if axis == "ray":  # the model already measures along the ray: no axis factor
        coss_for_axis = np.where(coss > 0, 1.0, 0.0).astype(np.float32)
    else:
        coss_for_axis = coss
    if align:
        scales, shifts = align_faces(vals, coss_for_axis, kind)
    else:
        scales, shifts = np.ones(6), np.zeros(6)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = vals * scales[:, None, None] + shifts[:, None, None]
        ray = z * coss_for_axis if kind == "disparity" else z / coss_for_axis
    weight = np.where(np.isfinite(ray), np.maximum(coss, 0) ** 8, 0.0)
    total = weight.sum(0)
    out = np.where(
        total > 0, np.nansum(np.nan_to_num(ray) * weight, 0) / np.where(total > 0, total, 1), np.nan
    )
    return out.astype(np.float32), {"face_scales": scales.tolist(), "face_shifts": shifts.tolist()}


def run_cubemap(model, rgb: np.ndarray, out_hw: tuple[int, int]) -> tuple[np.ndarray, dict]:
    """A perspective model (an OnnxDepthModel with projection 'cubemap') on a panorama's cube faces."""
    c = model.contract
    size = model.input_hw(rgb.shape[:2])[0]
    faces = []
    for name in FACE_NAMES:
        face_rgb = sample_face(rgb, name, size, c.face_fov_deg)
        raw = model.predict(face_rgb, (size, size))
        if raw.shape != (size, size):
            raw = cv2.resize(raw, (size, size), interpolation=cv2.INTER_LINEAR)
        faces.append(raw)
    return stitch(np.stack(faces), c.output, c.face_fov_deg, out_hw, c.perspective_axis)
