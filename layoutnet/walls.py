"""Walls from layout boundary points: the Manhattan and Atlanta fits of layoutnet/postprocess.py.

Follows HorizonNet's post-processing (misc/post_proc.py): corner peaks split the columns into
walls, each wall votes for x = const or z = const, neighbouring walls of the same orientation are
merged or joined by an occluded connecting wall, corners are the intersections. Differences, all
written down in docs/layout.md: the Manhattan frame is estimated (HorizonNet expects pre-aligned
panoramas) and wall points come from both boundaries. Conventions as in postprocess.py: floor
polygons in the camera's (x, z) plane, metres, counter-clockwise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import median_filter
from scipy.optimize import minimize_scalar
from shapely.geometry import Point, Polygon
from shapely.geometry.polygon import orient

from panogeom.equirect import column_longitudes

__all__ = ["Wall", "dominant_yaw", "fit_manhattan", "fit_atlanta", "finish_polygon", "rotation_2d", "wall_segments",
           "walls_polygon"]


def wall_segments(corners: np.ndarray, n: int, margin: int) -> list[np.ndarray]:
    """Column indices of the wall between each corner and the next (circular),
    leaving `margin` columns out at both ends (they may see the next wall)."""
    segs = []
    k = len(corners)
    for j in range(k):
        a, b = int(corners[j]), int(corners[(j + 1) % k])
        if b <= a:
            b += n
        length = b - a
        m = min(margin, max((length - 2) // 2, 0))
        idx = np.arange(a + 1 + m, b - m) % n
        if idx.size == 0:
            idx = np.arange(a, b + 1) % n
        segs.append(idx)
    return segs


def _merge_close_corners(corners: np.ndarray, n: int, min_cols: int) -> np.ndarray:
    """Drop corners that leave a wall narrower than min_cols columns."""
    c = np.sort(np.unique(np.asarray(corners, dtype=int) % n))
    while len(c) > 3:
        gaps = (np.roll(c, -1) - c) % n
        j = int(np.argmin(gaps))
        if gaps[j] >= min_cols:
            break
        c = np.delete(c, (j + 1) % len(c))
    return c


# -- Manhattan frame ------------------------------------------------------------
def dominant_yaw(pts: np.ndarray, segments: list[np.ndarray]) -> float:
    """Rotation (rad, in [-pi/4, pi/4)) of the Manhattan frame: wall directions
    folded modulo 90 degrees, averaged as angles times four, weighted by the
    number of columns of each wall."""
    acc = np.zeros(2)
    for idx in segments:
        if idx.size < 3:
            continue
        p = pts[idx] - pts[idx].mean(axis=0)
        _, _, vt = np.linalg.svd(p, full_matrices=False)
        ang = np.arctan2(vt[0, 1], vt[0, 0])
        acc += idx.size * np.array([np.cos(4 * ang), np.sin(4 * ang)])
    if not np.any(acc):
        return 0.0
    return float(np.arctan2(acc[1], acc[0]) / 4)


def rotation_2d(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s], [s, c]])


def _vote(v: np.ndarray, tol: float) -> tuple[float, float, float]:
    """(value, score, l1): the largest cluster of values within tol, its mean,
    the fraction of values in it, and the mean |v - value| (HorizonNet's vote)."""
    v = np.sort(np.asarray(v, dtype=np.float64))
    if v.size == 0:
        return 0.0, 0.0, np.inf
    # For each start i, the last j with v[j] - v[i] <= tol (sliding window).
    j = np.searchsorted(v, v + tol, side="right") - 1
    count = j - np.arange(v.size) + 1
    i = int(np.argmax(count))
    value = float(v[i : j[i] + 1].mean())
    return value, float(count[i] / v.size), float(np.abs(v - value).mean())


_RAY = -1  # a Wall "axis" for an edge along an occluding ray (its val: the longitude)


@dataclass
class Wall:
    axis: int  # 0: x = val, 1: z = val (in the Manhattan frame)
    val: float
    score: float
    n: int
    phi0: float  # longitude of the corner starting the wall
    phi1: float  # longitude of the corner ending it
    fixed: bool = False
    idx: np.ndarray | None = None  # its columns
    tol: float = 0.0  # its voting tolerance (grows with the boundary noise)


def _ray_hit(axis: int, val: float, phi: float) -> np.ndarray | None:
    """Where the ray at longitude phi (in the Manhattan frame) meets the line."""
    d = np.array([np.sin(phi), np.cos(phi)])
    if abs(d[axis]) < 1e-9:
        return None
    t = val / d[axis]
    return t * d if t > 0 else None


def _absorb_weak_walls(walls: list[Wall], q: np.ndarray, min_cols: int, tol: float) -> list[Wall]:
    """Walls seen over few columns (noise splits walls into such pieces). A weak wall
    whose points a neighbour's line explains about as well as its own line is a
    false split and is dropped; otherwise it is a short real wall (a jamb, a wall
    seen through a doorway) and stays with its own orientation vote."""
    while len(walls) > 4:
        weak = [j for j, w in enumerate(walls) if 0 < w.n < min_cols and not w.fixed]
        if not weak:
            break
        j = min(weak, key=lambda j: walls[j].n)
        p, w, nx = walls[j - 1], walls[j], walls[(j + 1) % len(walls)]
        # On a neighbour: that line explains its points about as well as its own does.
        own = float(np.mean(np.abs(q[w.idx, w.axis] - w.val)))
        on_neighbour = min(float(np.mean(np.abs(q[w.idx, v.axis] - v.val))) for v in (p, nx))
        if on_neighbour <= max(tol / 2, 1.5 * own):
            del walls[j]
        else:  # a short real wall, e.g. one seen through a doorway: keep its own vote
            w.fixed = True
    return walls


def _line_t(c: np.ndarray, d: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """Distance along the rays at longitudes phi to the line c + s d (inf: parallel or behind)."""
    r = np.stack([np.sin(phi), np.cos(phi)], axis=-1)
    den = r[..., 0] * d[1] - r[..., 1] * d[0]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (c[0] * d[1] - c[1] * d[0]) / den
    return np.where((np.abs(den) > 1e-12) & (t > 0), t, np.inf)


def _axis_line(axis: int, val: float) -> tuple[np.ndarray, np.ndarray]:
    return (
        (np.array([val, 0.0]), np.array([0.0, 1.0]))
        if axis == 0
        else (np.array([0.0, val]), np.array([1.0, 0.0]))
    )


def _occlusion_phi(q: np.ndarray, phis: np.ndarray, a, b, phi_a: float, phi_b: float, pad: float) -> float:
    """Longitude where wall a's columns end and wall b's begin: midway between the
    last column that line a explains better and the first that line b does (the
    corner peak itself can be a column off, which moves a hidden wall by d*dphi)."""
    two_pi = 2 * np.pi
    span = (phi_b - phi_a) % two_pi
    rel = (phis - (phi_a - pad)) % two_pi
    sel = np.flatnonzero(rel <= span + 2 * pad)
    if sel.size < 2:
        return phi_a
    sel = sel[np.argsort(rel[sel])]
    r = np.linalg.norm(q[sel], axis=1)
    on_b = np.abs(r - _line_t(*b, phis[sel])) < np.abs(r - _line_t(*a, phis[sel]))
    # Split minimising the columns on the wrong side of it.
    cost = np.concatenate([[0], np.cumsum(on_b)]) + np.concatenate([np.cumsum((~on_b)[::-1])[::-1], [0]])
    k = int(np.argmin(cost))
    step = two_pi / len(phis)
    if k == 0:
        return float(phis[sel[0]] - step / 2)
    if k == sel.size:
        return float(phis[sel[-1]] + step / 2)
    return float(phis[sel[k - 1]] + 0.5 * (((phis[sel[k]] - phis[sel[k - 1]]) + np.pi) % two_pi - np.pi))


def _resolve_manhattan(
    walls: list[Wall],
    tol: float,
    q: np.ndarray | None = None,
    phis: np.ndarray | None = None,
    pad: float = 0.0,
) -> list[Wall]:
    """Make orientations alternate: merge neighbouring parallel walls that are
    close (a false corner), otherwise join them at the nearer wall's visible end:
    by a perpendicular wall hidden behind it (HorizonNet), or, when the camera
    would see that wall, by an edge along the occluding ray."""
    changed = True
    while changed and len(walls) > 1:
        changed = False
        for j in range(len(walls)):
            a, b = walls[j], walls[(j + 1) % len(walls)]
            if a.axis != b.axis:
                continue
            if abs(a.val - b.val) <= tol or len(walls) <= 2:
                w = max(a.n + b.n, 1)
                val = (a.val * max(a.n, 1e-9) + b.val * max(b.n, 1e-9)) / (max(a.n, 1e-9) + max(b.n, 1e-9))
                walls[j] = Wall(a.axis, val, max(a.score, b.score), w, a.phi0, b.phi1, tol=max(a.tol, b.tol))
                del walls[(j + 1) % len(walls)]
            else:
                # The hidden wall starts where the nearer wall's visible end is.
                if q is not None:
                    phi = _occlusion_phi(
                        q, phis, _axis_line(a.axis, a.val), _axis_line(b.axis, b.val), a.phi1, b.phi0, pad
                    )
                    ha, hb = _ray_hit(a.axis, a.val, phi), _ray_hit(b.axis, b.val, phi)
                else:
                    ha, hb = _ray_hit(a.axis, a.val, a.phi1), _ray_hit(b.axis, b.val, b.phi0)
                    phi = a.phi1
                cands = [h for h in (ha, hb) if h is not None]
                if not cands:
                    return []
                near = min(cands, key=lambda h: float(np.hypot(*h)))
                other = 1 - a.axis
                # The connector runs from `near` to the far wall; it must stay behind the
                # near wall (unseen), else the camera sees past it (a doorway): then the
                # room's outline follows the occluding ray instead.
                far = near.copy()
                far[a.axis] = b.val if near is ha else a.val
                side = np.angle(np.exp(1j * (np.arctan2(far[0], far[1]) - phi)))
                if (side <= 1e-9) if near is ha else (side >= -1e-9):
                    walls.insert(j + 1, Wall(other, float(near[other]), 0.0, 0, a.phi1, b.phi0))
                else:
                    walls.insert(j + 1, Wall(_RAY, float(phi), 0.0, 0, phi, phi))
            changed = True
            break
    return walls


def _complete_occlusions(walls: list[Wall], q: np.ndarray, phis: np.ndarray, pad: float) -> list[Wall]:
    """Perpendicular neighbours that do not meet where the boundary switches from
    one to the other: the nearer wall's end hides part of the room (HorizonNet
    would intersect them, cutting through the hidden part or the visible far
    wall). The outline then follows the occluding ray from the near wall's end to
    the far wall: the visible room only, because a guessed hidden corner can be
    metres off, and the union of views only ever adds area."""
    j = 0
    while j < len(walls) and len(walls) < 64:
        a, b = walls[j], walls[(j + 1) % len(walls)]
        if a.axis == b.axis or a.n == 0 or b.n == 0:
            j += 1
            continue
        x = np.zeros(2)
        x[a.axis], x[b.axis] = a.val, b.val
        phi_t = _occlusion_phi(
            q, phis, _axis_line(a.axis, a.val), _axis_line(b.axis, b.val), a.phi1, b.phi0, pad
        )
        # At real corners the two differ by < 5 columns even with a pixel of noise
        # (measured); an occluding corner hides tens of columns.
        mismatch = abs(np.angle(np.exp(1j * (np.arctan2(x[0], x[1]) - phi_t))))
        if (
            mismatch <= 2 * pad
            or _ray_hit(a.axis, a.val, phi_t) is None
            or _ray_hit(b.axis, b.val, phi_t) is None
        ):
            j += 1
            continue
        walls.insert(j + 1, Wall(_RAY, float(phi_t), 0.0, 0, phi_t, phi_t))
        j += 2
    return walls


def walls_polygon(walls: list[Wall]) -> np.ndarray:
    """Corners of alternating axis-aligned walls, in wall order; an occluding-ray
    edge between two walls gives their ends on that ray."""
    pts = []
    for j in range(len(walls)):
        a, b = walls[j], walls[(j + 1) % len(walls)]
        if a.axis == _RAY or b.axis == _RAY:
            ray, wall = (a, b) if a.axis == _RAY else (b, a)
            hit = _ray_hit(wall.axis, wall.val, ray.val)
            pts.append(hit if hit is not None else np.full(2, np.nan))
            continue
        p = np.zeros(2)
        p[a.axis] = a.val
        p[b.axis] = b.val
        pts.append(p)
    return np.asarray(pts)


def finish_polygon(poly: np.ndarray) -> np.ndarray | None:
    """CCW polygon if it is a valid room around the camera, else None."""
    if poly is None or len(poly) < 3 or not np.all(np.isfinite(poly)):
        return None
    shape = Polygon(poly)
    if not shape.is_valid or shape.area < 1e-6 or not shape.contains(Point(0.0, 0.0)):
        return None
    return np.asarray(orient(shape, sign=1.0).exterior.coords)[:-1]


def _refine_yaw(pts: np.ndarray, segs: list[np.ndarray], yaw0: float, span: float = np.radians(4)) -> float:
    """Yaw minimising the spread of each wall's constant coordinate. PCA of a
    wall seen at a slant is biased by the (radial) boundary noise; this spread
    is not, to first order."""
    segs = [s for s in segs if s.size >= 3]
    if not segs:
        return yaw0
    q0 = pts @ rotation_2d(-yaw0).T
    axes = []
    for idx in segs:
        ext = np.ptp(q0[idx], axis=0)
        axes.append(0 if ext[0] < ext[1] else 1)

    # Latitude noise moves a point by ~d^2: weight deviations by 1/d^2.
    wgt = 1.0 / np.maximum(np.einsum("ij,ij->i", pts, pts), 1e-6)

    def cost(y: float) -> float:
        q = pts @ rotation_2d(-y).T
        total = 0.0
        for idx, ax in zip(segs, axes):
            v = q[idx, ax]
            total += float((np.abs(v - np.median(v)) * wgt[idx]).sum())
        return total

    res = minimize_scalar(cost, bounds=(yaw0 - span, yaw0 + span), method="bounded", options={"xatol": 1e-5})
    return float(res.x) if res.success else yaw0


def fit_manhattan(
    pts: np.ndarray, corners: np.ndarray, tol: float, margin: int | None = None
) -> np.ndarray | None:
    """HorizonNet-style Manhattan walls from wall-foot points [W,2] and corner
    columns. Returns the CCW polygon or None when no valid one results."""
    n = len(pts)
    corners = _merge_close_corners(corners, n, max(3, n // 128))
    if len(corners) < 4:
        return None
    if margin is None:
        margin = max(1, n // 256)
    segs = wall_segments(corners, n, margin)
    yaw = _refine_yaw(pts, segs, dominant_yaw(pts, segs))
    q = pts @ rotation_2d(-yaw).T  # into the Manhattan frame
    # Rotating by -yaw about the vertical adds yaw to every longitude.
    cphi = column_longitudes(n)[corners] + yaw
    # Boundary noise, as a radial spread per column (a latitude error moves a wall
    # point by ~d^2): votes use at least 2.5 sigma, so noise does not split walls.
    d = np.linalg.norm(pts, axis=1)
    ds = median_filter(d, size=max(3, (n // 64) | 1), mode="wrap")
    sigma = 1.4826 * float(np.median(np.abs(d - ds) / np.maximum(ds, 1e-6) ** 2)) * d**2
    walls: list[Wall] = []
    k = len(corners)
    for j, idx in enumerate(segs):
        tj = max(tol, 2.5 * float(np.median(sigma[idx])))
        vx, sx, lx = _vote(q[idx, 0], tj)
        vz, sz, lz = _vote(q[idx, 1], tj)
        axis, val, score = (0, vx, sx) if (sx, -lx) > (sz, -lz) else (1, vz, sz)
        walls.append(
            Wall(axis, val, score, idx.size, float(cphi[j]), float(cphi[(j + 1) % k]), idx=idx, tol=tj)
        )
    walls = _absorb_weak_walls(walls, q, max(3, n // 40), tol)
    phis = column_longitudes(n) + yaw
    pad = (margin + 2) * 2 * np.pi / n
    walls = _resolve_manhattan(walls, tol, q, phis, pad)
    walls = _complete_occlusions(walls, q, phis, pad)
    if len(walls) < 4:
        return None
    poly = walls_polygon(walls) @ rotation_2d(yaw).T
    return finish_polygon(poly)


def _fit_line(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Total least squares line (centre, unit direction), refitted once without outliers."""
    for _ in range(2):
        c = p.mean(axis=0)
        _, _, vt = np.linalg.svd(p - c, full_matrices=False)
        d = vt[0]
        r = np.abs((p - c) @ np.array([-d[1], d[0]]))
        mad = np.median(r)
        keep = r <= max(3.0 * 1.4826 * mad, 1e-9)
        if keep.sum() < 2 or keep.all():
            break
        p = p[keep]
    return c, d


def _intersect(c1, d1, c2, d2) -> np.ndarray | None:
    m = np.array([d1, -d2]).T
    if abs(np.linalg.det(m)) < 1e-9:
        return None
    t = np.linalg.solve(m, c2 - c1)
    return c1 + t[0] * d1


def fit_atlanta(
    pts: np.ndarray, corners: np.ndarray, tol: float, margin: int | None = None, parallel_deg: float = 10.0
) -> np.ndarray | None:
    """Walls at any angle (Atlanta world): a line per wall, corners where
    neighbouring lines meet; nearly parallel neighbours are merged when close,
    else joined by a hidden connecting wall on the corner's ray."""
    n = len(pts)
    corners = _merge_close_corners(corners, n, max(3, n // 128))
    if len(corners) < 3:
        return None
    if margin is None:
        margin = max(1, n // 256)
    segs = wall_segments(corners, n, margin)
    phi = column_longitudes(n)
    # Each wall: its columns (empty for an inferred connector), its line, and
    # the longitude of the corner that ends it.
    lines = []
    for j, idx in enumerate(segs):
        c, d = _fit_line(pts[idx])
        lines.append(
            {
                "idx": idx,
                "c": c,
                "d": d,
                "phi_start": float(phi[corners[j]]),
                "phi_end": float(phi[corners[(j + 1) % len(corners)]]),
            }
        )
    cos_par = np.cos(np.radians(parallel_deg))
    # Walls seen over few columns have unreliable directions: drop them and let
    # their neighbours meet (or be joined below when they are parallel).
    min_cols = max(3, n // 40)

    def off(ln, p):  # distances of points p from the line ln
        return np.abs((p - ln["c"]) @ np.array([-ln["d"][1], ln["d"][0]]))

    while len(lines) > 3:
        weak = [j for j, ln in enumerate(lines) if ln["idx"].size < min_cols and not ln.get("kept")]
        if not weak:
            break
        j = min(weak, key=lambda j: lines[j]["idx"].size)
        p = pts[lines[j]["idx"]]
        on_neighbour = max(float(np.mean(off(lines[i % len(lines)], p) <= tol)) for i in (j - 1, j + 1))
        if on_neighbour >= 0.5:
            del lines[j]
        else:
            lines[j]["kept"] = True
    changed = True
    while changed and len(lines) >= 3:
        changed = False
        for j in range(len(lines)):
            a, b = lines[j], lines[(j + 1) % len(lines)]
            if abs(float(a["d"] @ b["d"])) < cos_par:
                continue
            normal = np.array([-a["d"][1], a["d"][0]])
            if abs(float((b["c"] - a["c"]) @ normal)) <= tol and a["idx"].size and b["idx"].size:
                idx = np.concatenate([a["idx"], b["idx"]])
                c, d = _fit_line(pts[idx])
                lines[j] = {"idx": idx, "c": c, "d": d, "phi_start": a["phi_start"], "phi_end": b["phi_end"]}
                del lines[(j + 1) % len(lines)]
            else:
                # The hidden wall starts where the nearer wall's visible end is.
                ph = _occlusion_phi(
                    pts,
                    phi,
                    (a["c"], a["d"]),
                    (b["c"], b["d"]),
                    a["phi_end"],
                    b["phi_start"],
                    (margin + 2) * 2 * np.pi / n,
                )
                ray = np.array([np.sin(ph), np.cos(ph)])
                hits = []
                for ln in (a, b):
                    p = _intersect(np.zeros(2), ray, ln["c"], ln["d"])
                    if p is not None and float(p @ ray) > 0:
                        hits.append(p)
                if not hits:
                    return None
                near_i = int(np.argmin([float(np.hypot(*p)) for p in hits]))
                near = hits[near_i]
                # Perpendicular to the near wall if that stays unseen behind it, else
                # along the occluding ray (the camera sees past the wall's end).
                direction = normal
                if len(hits) == 2:
                    other = b if near_i == 0 else a
                    far = _intersect(near, normal, other["c"], other["d"])
                    if far is not None:
                        side = np.angle(np.exp(1j * (np.arctan2(far[0], far[1]) - ph)))
                        if (side > 1e-9) if near_i == 0 else (side < -1e-9):
                            direction = ray
                conn = {
                    "idx": np.zeros(0, dtype=int),
                    "c": near,
                    "d": direction,
                    "phi_start": a["phi_end"],
                    "phi_end": b["phi_start"],
                }
                lines.insert(j + 1, conn)
            changed = True
            break
    if len(lines) < 3:
        return None
    # Neighbours that do not meet where the boundary switches between them: the
    # nearer one's end hides part of the room; the outline follows that ray.
    pad = (margin + 2) * 2 * np.pi / n
    j = 0
    while j < len(lines) and len(lines) < 64:
        a, b = lines[j], lines[(j + 1) % len(lines)]
        x = _intersect(a["c"], a["d"], b["c"], b["d"]) if a["idx"].size and b["idx"].size else None
        if x is not None:
            ph = _occlusion_phi(
                pts, phi, (a["c"], a["d"]), (b["c"], b["d"]), a["phi_end"], b["phi_start"], pad
            )
            if abs(np.angle(np.exp(1j * (np.arctan2(x[0], x[1]) - ph)))) > 2 * pad:
                ray = np.array([np.sin(ph), np.cos(ph)])
                lines.insert(
                    j + 1,
                    {
                        "idx": np.zeros(0, dtype=int),
                        "c": np.zeros(2),
                        "d": ray,
                        "phi_start": ph,
                        "phi_end": ph,
                    },
                )
                j += 1
        j += 1
    corners_xz = []
    for j in range(len(lines)):
        a, b = lines[j], lines[(j + 1) % len(lines)]
        p = _intersect(a["c"], a["d"], b["c"], b["d"])
        if p is None:
            return None
        corners_xz.append(p)
    return finish_polygon(np.asarray(corners_xz))
