"""Layout boundaries → a metric room, as pure numpy functions.

Conventions (DESIGN.md): camera frame x right, y down, z forward; a column's
longitude phi = atan2(x, z); boundaries are latitudes theta per column, the
ceiling boundary above the horizon (theta > 0), the floor boundary below it.
Floor polygons are in the camera's (x, z) plane, metres, counter-clockwise in
(x, z) (positive shoelace area). The camera is assumed level (gravity along
camera +y), as HorizonNet assumes.

The walls are fitted in layoutnet/walls.py (HorizonNet's post-processing, with
the differences docs/layout.md lists); a polygon that fails validation falls
back to a cuboid and then to the raw (star-shaped, always valid) outline
instead of failing.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from scipy.ndimage import maximum_filter, median_filter
from shapely.geometry import Polygon
from shapely.geometry.polygon import orient

from layoutnet.walls import (
    Wall,
    dominant_yaw,
    finish_polygon,
    fit_atlanta,
    fit_manhattan,
    rotation_2d,
    wall_segments,
    walls_polygon,
)
from panogeom.equirect import column_longitudes

DEFAULT_CAMERA_HEIGHT = 1.6  # HorizonNet's convention when the height is unknown (m)

#: Keep boundaries this far (rad) from the horizon and the poles so that
#: 1/tan stays finite (HorizonNet clips the rows the same way).
_EPS = 1e-3

Mode = Literal["manhattan", "cuboid", "atlanta"]
WallSource = Literal["both", "ceiling", "floor"]
#: The wall fit's defaults (HorizonNet's post-processing); the layout stage's settings take them
DEFAULT_MODE: Mode = "manhattan"
DEFAULT_WALL_SOURCE: WallSource = "both"
PEAK_R = 0.05  # corner non-maximum suppression window, a fraction of the width x2 (HorizonNet's r)
PEAK_MIN = 0.05  # minimum corner probability

__all__ = [
    "DEFAULT_CAMERA_HEIGHT",
    "DEFAULT_MODE",
    "DEFAULT_WALL_SOURCE",
    "PEAK_R",
    "PEAK_MIN",
    "RoomLayout",
    "check_boundaries",
    "estimate_ceiling_distance",
    "boundary_points",
    "find_peaks_circular",
    "corner_signal_from_points",
    "dominant_yaw",
    "fit_manhattan",
    "fit_cuboid",
    "fit_atlanta",
    "raw_polygon",
    "polygon_to_boundaries",
    "corners_to_polygon",
    "column_confidence",
    "layout_from_boundaries",
    "resample_boundaries",
]


@dataclass
class RoomLayout:
    """A metric room in the camera frame."""

    polygon: np.ndarray  # [K,2] (x, z) metres, counter-clockwise
    camera_height: float  # floor at camera y = +camera_height
    ceiling_distance: float  # ceiling at camera y = -ceiling_distance
    method: str  # what was fitted in the end: manhattan / cuboid / atlanta / raw / corners
    notes: list[str] = field(default_factory=list)  # fallbacks taken, for ctx.warn

    @property
    def room_height(self) -> float:
        return self.camera_height + self.ceiling_distance


# -- boundaries ---------------------------------------------------------------
def check_boundaries(boundaries: np.ndarray) -> np.ndarray:
    """Validate [2,W] latitudes (ceiling > 0 > floor) and clip them away from 0 and ±pi/2."""
    b = np.asarray(boundaries, dtype=np.float64)
    if b.ndim != 2 or b.shape[0] != 2 or b.shape[1] < 8:
        raise ValueError(f"boundaries must be [2,W] with W >= 8, got shape {list(b.shape)}")
    if not np.all(np.isfinite(b)):
        raise ValueError("boundaries contain NaN or Inf")
    out = b.copy()
    out[0] = np.clip(b[0], _EPS, np.pi / 2 - _EPS)
    out[1] = np.clip(b[1], -np.pi / 2 + _EPS, -_EPS)
    return out


def mean_percentile(v: np.ndarray, lo: float = 25, hi: float = 75) -> float:
    """Mean of the values between two percentiles (HorizonNet's robust mean)."""
    v = np.asarray(v, dtype=np.float64)
    a, b = np.percentile(v, [lo, hi])
    sel = v[(v >= a) & (v <= b)]
    return float(sel.mean() if sel.size else np.median(v))


def estimate_ceiling_distance(boundaries: np.ndarray, camera_height: float) -> float:
    """Camera-to-ceiling distance from both boundaries: per column the floor
    boundary gives the wall distance, the ceiling boundary at that distance the
    ceiling; a robust mean (25-75 percentile) over columns rejects outliers."""
    b = check_boundaries(boundaries)
    d = camera_height / np.tan(-b[1])
    return mean_percentile(d * np.tan(b[0]))


def boundary_points(
    boundaries: np.ndarray, camera_height: float, ceiling_distance: float, source: WallSource = "both"
) -> np.ndarray:
    """Per-column wall-foot points [W,2] (x, z) from the boundaries."""
    b = check_boundaries(boundaries)
    d_floor = camera_height / np.tan(-b[1])
    d_ceil = ceiling_distance / np.tan(b[0])
    d = {"both": 0.5 * (d_floor + d_ceil), "ceiling": d_ceil, "floor": d_floor}[source]
    phi = column_longitudes(b.shape[1])
    return np.stack([d * np.sin(phi), d * np.cos(phi)], axis=1)


def resample_boundaries(boundaries: np.ndarray, width: int) -> np.ndarray:
    """Boundaries at another width, interpolated periodically in longitude."""
    b = np.asarray(boundaries, dtype=np.float64)
    w0 = b.shape[1]
    if w0 == width:
        return b.copy()
    src = column_longitudes(w0)
    dst = column_longitudes(width)
    return np.stack([np.interp(dst, src, row, period=2 * np.pi) for row in b])


# -- corners ------------------------------------------------------------------
def find_peaks_circular(
    signal: np.ndarray, r: float = PEAK_R, min_v: float = PEAK_MIN, n: int | None = None
) -> np.ndarray:
    """Column indices of local maxima of a periodic signal (circular non-maximum
    suppression in a window of r*W/2 columns, as HorizonNet's find_N_peaks),
    above min_v; with n, the n highest. Sorted by column."""
    s = np.asarray(signal, dtype=np.float64)
    w = s.size
    size = max(int(round(w * r / 2)), 1)
    mx = maximum_filter(s, size=size, mode="wrap")
    pk = np.flatnonzero((mx == s) & (s > min_v))
    # A flat top yields several equal maxima: keep the first of each run.
    if pk.size > 1:
        keep = [pk[0]]
        for p in pk[1:]:
            if p - keep[-1] >= size or s[p] != s[keep[-1]]:
                keep.append(p)
        if len(keep) > 1 and (keep[0] + w - keep[-1]) < size and s[keep[0]] == s[keep[-1]]:
            keep.pop()
        pk = np.asarray(keep)
    if n is not None and pk.size > n:
        pk = pk[np.argsort(-s[pk], kind="stable")[:n]]
    return np.sort(pk)


def _dp_closed(pts: np.ndarray, eps: float | np.ndarray) -> dict[int, float]:
    """Douglas-Peucker on a closed polyline (eps per point or global): kept
    vertex index -> its deviation. Starts from the two points farthest apart
    (approximately), which are vertices of any simplification."""
    n = len(pts)
    eps = np.broadcast_to(np.asarray(eps, dtype=np.float64), (n,))
    i0 = int(np.argmax(np.linalg.norm(pts - pts.mean(axis=0), axis=1)))
    i1 = int(np.argmax(np.linalg.norm(pts - pts[i0], axis=1)))
    i0, i1 = min(i0, i1), max(i0, i1)
    kept: dict[int, float] = {i0: np.inf, i1: np.inf}

    def rec(a: int, b: int) -> None:  # indices along the closed loop, a < b (b may exceed n)
        if b - a < 2:
            return
        idx = np.arange(a + 1, b) % n
        pa, pb = pts[a % n], pts[b % n]
        seg = pb - pa
        L = np.hypot(*seg)
        rel = pts[idx] - pa
        dist = (
            np.abs(seg[0] * rel[:, 1] - seg[1] * rel[:, 0]) / L if L > 1e-12 else np.linalg.norm(rel, axis=1)
        )
        k = int(np.argmax(dist - eps[idx]))
        if dist[k] > eps[idx[k]]:
            m = a + 1 + k
            kept[m % n] = float(dist[k])
            rec(a, m)
            rec(m, b)

    rec(i0, i1)
    rec(i1, i0 + n)
    return kept


def corner_signal_from_points(pts: np.ndarray, eps: float | None = None) -> np.ndarray:
    """A corner score per column when no `cor` output exists (supplied .npy
    boundaries): vertices of a Douglas-Peucker simplification of the wall-foot
    outline, scored by how far they stand out of the line joining their
    neighbours (so the most significant are the first taken for a cuboid).
    The outline is median-filtered first and the tolerance grows with the
    noise it measures, so that boundary noise does not make corners."""
    pts = np.asarray(pts, dtype=np.float64)
    n = len(pts)
    d = np.linalg.norm(pts, axis=1)
    k = max(3, (n // 64) | 1)
    ds = median_filter(d, size=k, mode="wrap")
    if eps is None:
        # A fixed latitude error moves a far wall more (~d^2), so the noise is
        # measured relative to d^2 and the tolerance grows with it per column;
        # 1.25/sqrt(k): what the median filter leaves of it.
        rel = 1.4826 * float(np.median(np.abs(d - ds) / ds**2)) * 1.25 / np.sqrt(k)
        eps = np.maximum(max(0.03, 0.015 * float(np.median(d))), 5.0 * rel * ds**2)
    phi = column_longitudes(n)
    sm = np.stack([ds * np.sin(phi), ds * np.cos(phi)], axis=1)
    kept = sorted(_dp_closed(sm, eps))
    sig = np.zeros(n)
    if len(kept) < 3:
        return sig
    for j, c in enumerate(kept):
        a, b = sm[kept[j - 1]], sm[kept[(j + 1) % len(kept)]]
        seg = b - a
        L = np.hypot(*seg)
        rel = sm[c] - a
        sig[c] = abs(seg[0] * rel[1] - seg[1] * rel[0]) / L if L > 1e-12 else np.hypot(*rel)
    # Map to (0, 1] so find_peaks_circular's thresholds mean the same thing.
    return sig / max(sig.max(), 1e-12)


def fit_cuboid(pts: np.ndarray, corners: np.ndarray, margin: int | None = None) -> np.ndarray | None:
    """Four walls, alternating orientation, from the four strongest corners."""
    n = len(pts)
    corners = np.sort(np.asarray(corners, dtype=int) % n)
    if len(corners) != 4:
        return None
    if margin is None:
        margin = max(1, n // 256)
    segs = wall_segments(corners, n, margin)
    yaw = dominant_yaw(pts, segs)
    q = pts @ rotation_2d(-yaw).T
    # Walls 0 and 2 share an orientation: pick the phase with the smaller spread.
    best = None
    for phase in (0, 1):
        vals, spread = [], 0.0
        for j, idx in enumerate(segs):
            axis = (j + phase) % 2
            v = float(np.median(q[idx, axis]))
            vals.append((axis, v))
            spread += float(np.abs(q[idx, axis] - v).mean()) * idx.size
        if best is None or spread < best[0]:
            best = (spread, vals)
    walls = [Wall(a, v, 1.0, 1, 0.0, 0.0) for a, v in best[1]]
    poly = walls_polygon(walls) @ rotation_2d(yaw).T
    return finish_polygon(poly)


def raw_polygon(pts: np.ndarray, eps: float = 0.01) -> np.ndarray:
    """The per-column outline itself, lightly simplified: star-shaped around the
    camera, so always a valid room (the last-resort fallback)."""
    kept = sorted(_dp_closed(np.asarray(pts, dtype=np.float64), eps))
    poly = finish_polygon(pts[kept]) if len(kept) >= 3 else None
    return poly if poly is not None else np.asarray(orient(Polygon(pts), sign=1.0).exterior.coords)[:-1]


# -- corners given (HorizonNet JSON, corner .txt) ------------------------------
def corners_to_polygon(
    phi: np.ndarray,
    theta_ceil: np.ndarray,
    theta_floor: np.ndarray,
    camera_height: float,
    ceiling_distance: float,
) -> np.ndarray:
    """Floor polygon from corners given as (phi, ceiling latitude, floor latitude):
    each corner's distance is the mean of what its floor and ceiling points say.
    The corners are taken in the order given (HorizonNet writes them in wall order,
    which is not always increasing u: a wall can be seen from behind its end), else
    sorted by longitude when that order does not make a simple polygon."""
    tc = np.clip(np.asarray(theta_ceil, dtype=np.float64), _EPS, np.pi / 2 - _EPS)
    tf = np.clip(np.asarray(theta_floor, dtype=np.float64), -np.pi / 2 + _EPS, -_EPS)
    d = 0.5 * (camera_height / np.tan(-tf) + ceiling_distance / np.tan(tc))
    phi = np.asarray(phi, dtype=np.float64)
    pts = np.stack([d * np.sin(phi), d * np.cos(phi)], axis=1)
    for cand in (pts, pts[np.argsort(phi, kind="stable")]):
        shape = Polygon(cand)
        if shape.is_valid and shape.area > 0:
            return np.asarray(orient(shape, sign=1.0).exterior.coords)[:-1]
    raise ValueError("the corners do not form a simple polygon")


# -- polygon → boundaries ------------------------------------------------------
def polygon_to_boundaries(
    polygon: np.ndarray, camera_height: float, ceiling_distance: float, width: int
) -> np.ndarray:
    """Ray-cast the room from the camera: [2,W] ceiling/floor latitudes.
    Columns whose ray misses the polygon (camera outside) get NaN."""
    poly = np.asarray(polygon, dtype=np.float64)
    phi = column_longitudes(width)
    d = np.stack([np.sin(phi), np.cos(phi)], axis=1)  # [W,2]
    a = poly
    e = np.roll(poly, -1, axis=0) - poly  # [E,2]
    # Solve t d = a + s e  →  t (d × e) = a × e,  s (d × e) = a × d.
    cross = d[:, None, 0] * e[None, :, 1] - d[:, None, 1] * e[None, :, 0]  # [W,E]
    a_x_e = a[None, :, 0] * e[None, :, 1] - a[None, :, 1] * e[None, :, 0]
    a_x_d = a[None, :, 0] * d[:, None, 1] - a[None, :, 1] * d[:, None, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = a_x_e / cross
        s = a_x_d / cross
    ok = (np.abs(cross) > 1e-12) & (t > 1e-9) & (s >= -1e-9) & (s <= 1 + 1e-9)
    t = np.where(ok, t, np.inf).min(axis=1)
    t[~np.isfinite(t)] = np.nan
    return np.stack([np.arctan2(ceiling_distance, t), -np.arctan2(camera_height, t)])


def column_confidence(raw: np.ndarray, fitted: np.ndarray, sigma: float = 2.0 * np.pi / 512) -> np.ndarray:
    """[W] in [0,1]: how well the fitted room explains each column's raw
    boundaries, exp(-(e/sigma)^2/2) with e the larger of the ceiling and floor
    latitude errors; sigma defaults to two rows of a 512-row panorama."""
    raw = np.asarray(raw, dtype=np.float64)
    fit = resample_boundaries(fitted, raw.shape[1])
    err = np.nanmax(np.abs(raw - fit), axis=0)
    err = np.where(np.isfinite(err), err, np.inf)
    return np.exp(-0.5 * (err / sigma) ** 2).astype(np.float32)


# -- the whole post-processing -------------------------------------------------
def layout_from_boundaries(
    boundaries: np.ndarray,
    camera_height: float = DEFAULT_CAMERA_HEIGHT,
    cor: np.ndarray | None = None,
    mode: Mode = DEFAULT_MODE,
    ceiling_distance: float | None = None,
    wall_source: WallSource = DEFAULT_WALL_SOURCE,
    peak_r: float = PEAK_R,
    peak_min: float = PEAK_MIN,
    tol: float | None = None,
) -> RoomLayout:
    """Boundaries [2,W] (+ optional corner probabilities `cor` [W'] in [0,1])
    → metric room. `tol` (m) is the wall voting/merging tolerance, by default
    a tenth of the camera height (HorizonNet: 0.16 * z1 / 1.6)."""
    b = check_boundaries(boundaries)
    n = b.shape[1]
    if camera_height <= 0:
        raise ValueError(f"camera height must be positive, got {camera_height}")
    if ceiling_distance is None:
        ceiling_distance = estimate_ceiling_distance(b, camera_height)
    pts = boundary_points(b, camera_height, ceiling_distance, wall_source)
    if tol is None:
        tol = 0.1 * camera_height
    notes: list[str] = []

    if cor is not None:
        sig = resample_boundaries(np.asarray(cor, dtype=np.float64)[None], n)[0]
        min_v = peak_min
    else:
        sig = corner_signal_from_points(pts)
        min_v = 1e-6
    poly = None
    method = mode
    if mode == "manhattan":
        poly = fit_manhattan(pts, find_peaks_circular(sig, peak_r, min_v), tol)
    elif mode == "atlanta":
        poly = fit_atlanta(pts, find_peaks_circular(sig, peak_r, min_v), tol)
    if poly is None:
        if mode != "cuboid":
            notes.append(f"{mode} wall fitting gave no valid room; fell back to a cuboid")
        poly = fit_cuboid(pts, find_peaks_circular(sig, peak_r, -np.inf, n=4))
        method = "cuboid"
    if poly is None:
        notes.append("no valid cuboid either; kept the raw boundary outline")
        poly = raw_polygon(pts)
        method = "raw"
    return RoomLayout(poly, float(camera_height), float(ceiling_distance), method, notes)
