"""Analytic, vectorised ray casting against the room shell and furniture boxes.

Surfaces get integer ids: 0 floor, 1 ceiling, 2 .. 2+len(walls)-1 walls (in
`World.walls` order), then one id per furniture box. Rays start at one origin
(a panorama's centre); directions are unit vectors in the world frame, so the
returned parameter t is the distance along the ray.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from simulate.geometry import Box, World

FLOOR, CEILING, WALL0 = 0, 1, 2
EPS = 1e-9


@dataclass
class Hits:
    t: np.ndarray  # [N] distance along the ray (inf = miss)
    sid: np.ndarray  # [N] int32 surface id
    box_axis: np.ndarray  # [N] int8: axis of the box face hit (0,1,2), -1 elsewhere


def box_id0(world: World) -> int:
    return WALL0 + len(world.walls)


def cast(
    origin: np.ndarray,
    dirs: np.ndarray,
    world: World,
    boxes: list[Box],
    timings: dict[str, float] | None = None,
    shell_key: str = "raycast",
    box_key: str = "furniture",
) -> Hits:
    """Nearest hit of each ray [N,3] from `origin` [3] with floor, ceiling, walls and `boxes`."""
    t0 = time.perf_counter()
    dt = dirs.dtype
    o = np.asarray(origin, dtype=np.float64)
    dx, dy, dz = dirs[:, 0], dirs[:, 1], dirs[:, 2]
    n = dirs.shape[0]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        # Floor (y = 0) when looking down (dy > 0), ceiling (y = -C) when looking up.
        inv_dy = 1.0 / dy
        down = dy > 0
        t = np.where(down, (0.0 - o[1]) * inv_dy, (world.ceiling_y - o[1]) * inv_dy)
        t = np.where(t > 0, t, np.inf).astype(dt, copy=False)
        sid = np.where(down, FLOOR, CEILING).astype(np.int32)
        # Vertical walls: 2D ray/segment test in (x, z), then the wall's y range.
        for k, wall in enumerate(world.walls):
            ex, ez = wall.b - wall.a
            wx, wz = wall.a[0] - o[0], wall.a[1] - o[2]
            denom = dx * ez - dz * ex
            inv = 1.0 / denom
            tw = (wx * ez - wz * ex) * inv
            s = (wx * dz - wz * dx) * inv
            hit = (tw > EPS) & (tw < t) & (s >= 0) & (s <= 1)
            if wall.y_top > world.ceiling_y or wall.y_bottom < 0:
                y = o[1] + tw * dy
                hit &= (y >= wall.y_top) & (y <= wall.y_bottom)
            t = np.where(hit, tw, t)
            sid[hit] = WALL0 + k
    t1 = time.perf_counter()
    axis = np.full(n, -1, dtype=np.int8)
    if boxes:
        base = box_id0(world)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            inv = [1.0 / dx, 1.0 / dy, 1.0 / dz]
            for j, bx in enumerate(boxes):
                tn = None
                tf = None
                ax = None
                for a in range(3):
                    t_lo = (bx.lo[a] - o[a]) * inv[a]
                    t_hi = (bx.hi[a] - o[a]) * inv[a]
                    tmin = np.minimum(t_lo, t_hi)
                    tmax = np.maximum(t_lo, t_hi)
                    if tn is None:
                        tn, tf, ax = tmin, tmax, np.zeros(n, dtype=np.int8)
                    else:
                        bigger = tmin > tn
                        tn = np.where(bigger, tmin, tn)
                        ax[bigger] = a
                        tf = np.minimum(tf, tmax)
                hit = (tn <= tf) & (tn > EPS) & (tn < t)
                t = np.where(hit, tn, t)
                sid[hit] = base + j
                axis[hit] = ax[hit]
    t2 = time.perf_counter()
    if timings is not None:
        timings[shell_key] = timings.get(shell_key, 0.0) + (t1 - t0)
        if boxes:
            timings[box_key] = timings.get(box_key, 0.0) + (t2 - t1)
    return Hits(t=t, sid=sid, box_axis=axis)


def normals(hits: Hits, dirs: np.ndarray, world: World, boxes: list[Box], origin: np.ndarray) -> np.ndarray:
    """Unit surface normals [N,3] facing the camera at `origin` (walls are two-sided): a table
    look-up per surface id (and box face axis), no per-ray arithmetic."""
    o = np.asarray(origin, dtype=np.float64)
    base = box_id0(world)
    table = np.zeros((base + len(boxes), 3))
    table[FLOOR] = (0.0, -1.0, 0.0)
    table[CEILING] = (0.0, 1.0, 0.0)
    for k, wall in enumerate(world.walls):
        ex, ez = (wall.b - wall.a) / wall.length
        n = np.array([-ez, 0.0, ex])
        if n[0] * (o[0] - wall.a[0]) + n[2] * (o[2] - wall.a[1]) < 0:
            n = -n
        table[WALL0 + k] = n
    n = table.astype(dirs.dtype)[hits.sid]
    bm = hits.box_axis >= 0
    if bm.any():
        btab = np.zeros((len(boxes), 3, 3))
        for j, bx in enumerate(boxes):
            centre = 0.5 * (bx.lo + bx.hi)
            for a in range(3):
                btab[j, a, a] = 1.0 if o[a] > centre[a] else -1.0
        n[bm] = btab.astype(dirs.dtype)[hits.sid[bm] - base, hits.box_axis[bm]]
    return n


# ----------------------------------------------------------------------------- fast path

LEVEL_TOL = 1e-9


def is_level(rot: np.ndarray) -> bool:
    """True when the camera's y axis is the world's (a level camera turned about +y only)."""
    y = np.array([0.0, 1.0, 0.0])
    return bool(np.abs(rot[:, 1] - y).max() < LEVEL_TOL and np.abs(rot[1] - y).max() < LEVEL_TOL)


def world_dirs(lat: np.ndarray, lon: np.ndarray, rot: np.ndarray, dtype=np.float64) -> np.ndarray:
    """[len(lat)*len(lon), 3] world ray directions R d(lon, lat), rows major
    (DESIGN.md: d = (cos lat sin lon, -sin lat, cos lat cos lon)), computed separably."""
    ct, st = np.cos(lat)[:, None], np.sin(lat)[:, None]
    sp, cp = np.sin(lon)[None, :], np.cos(lon)[None, :]
    out = np.empty((len(lat), len(lon), 3), dtype=dtype)
    for i in range(3):
        out[..., i] = (rot[i, 0] * sp + rot[i, 2] * cp) * ct - rot[i, 1] * st
    return out.reshape(-1, 3)


def _seg_dist_2d(
    ox: float, oz: float, hx: np.ndarray, hz: np.ndarray, a: np.ndarray, b: np.ndarray
) -> np.ndarray:
    """Distance along unit 2D rays (hx, hz) from (ox, oz) to segment (a, b); inf when missed."""
    ex, ez = b - a
    wx, wz = a[0] - ox, a[1] - oz
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = hx * ez - hz * ex
        t = (wx * ez - wz * ex) / denom
        s = (wx * hz - wz * hx) / denom
    return np.where((t > EPS) & (s >= 0) & (s <= 1), t, np.inf)


def _sorted_range(values: np.ndarray, lo: float, hi: float) -> list[tuple[int, int]]:
    i0 = int(np.searchsorted(values, lo, side="left"))
    i1 = int(np.searchsorted(values, hi, side="right"))
    return [(i0, i1)] if i1 > i0 else []


def _index_ranges(values: np.ndarray, lo: float, hi: float, periodic: bool = True) -> list[tuple[int, int]]:
    """Index ranges [i0, i1) of ascending longitudes `values` within [lo, hi], wrapping at +-pi."""
    if not periodic:
        return _sorted_range(values, lo, hi)
    if hi - lo >= 2 * np.pi:
        return [(0, len(values))]
    lo_w = (lo + np.pi) % (2 * np.pi) - np.pi
    hi_w = lo_w + (hi - lo)
    if hi_w <= np.pi:
        return _sorted_range(values, lo_w, hi_w)
    return _sorted_range(values, lo_w, np.pi) + _sorted_range(values, -np.pi, hi_w - 2 * np.pi)


def _lon_interval(ox: float, oz: float, pts: np.ndarray, rot: np.ndarray, pad: float) -> tuple[float, float]:
    """Camera-frame longitude interval [lo, hi] (hi - lo < 2 pi) covering 2D points `pts` [K,2]."""
    rel = np.stack([pts[:, 0] - ox, np.zeros(len(pts)), pts[:, 1] - oz], axis=1) @ rot  # world -> camera
    lon = np.arctan2(rel[:, 0], rel[:, 2])
    ref = lon[0]
    d = np.angle(np.exp(1j * (lon - ref)))
    if d.max() - d.min() >= np.pi - 1e-6:
        return -np.pi, np.pi  # camera on/inside the footprint: no culling
    return ref + d.min() - pad, ref + d.max() + pad


def cast_grid(
    origin: np.ndarray,
    rot: np.ndarray,
    lat: np.ndarray,
    lon: np.ndarray,
    world: World,
    boxes: list[Box],
    timings: dict[str, float] | None = None,
    shell_key: str = "raycast",
    box_key: str = "furniture",
    dtype=np.float64,
) -> tuple[Hits, np.ndarray]:
    """`cast` for the equirectangular grid of rows `lat` x columns `lon` (ascending lon,
    descending lat), returning (hits, world dirs [R*C,3]). For a level camera it uses the
    separable structure: floor/ceiling distance depends on the row only; a full-height wall's
    distance is s(column) / cos(lat(row)); lintels and boxes are tested only on the block of
    rows/columns they can cover. Exact: the same hits as `cast` (tested)."""
    dirs = world_dirs(lat, lon, rot, dtype)
    if not is_level(rot):
        return cast(origin, dirs, world, boxes, timings, shell_key, box_key), dirs
    t0 = time.perf_counter()
    o = np.asarray(origin, dtype=np.float64)
    nr, nc = len(lat), len(lon)
    ct, st = np.cos(lat), np.sin(lat)
    hx = rot[0, 0] * np.sin(lon) + rot[0, 2] * np.cos(lon)
    hz = rot[2, 0] * np.sin(lon) + rot[2, 2] * np.cos(lon)
    with np.errstate(divide="ignore", invalid="ignore"):
        # Ray y component is -sin(lat): floor (y = 0) below the horizon, ceiling above.
        t_row = np.where(st < 0, o[1] / st, (o[1] - world.ceiling_y) / st)
    t_row = np.where(t_row > 0, t_row, np.inf)
    sid_row = np.where(st < 0, FLOOR, CEILING).astype(np.int32)
    # Nearest full-height wall per column (2D), then the partial ones (lintels) on their columns.
    s_col = np.full(nc, np.inf)
    w_col = np.full(nc, -1, dtype=np.int32)
    partial = []
    for k, wall in enumerate(world.walls):
        if wall.y_top > world.ceiling_y or wall.y_bottom < 0:
            partial.append(k)
            continue
        s = _seg_dist_2d(o[0], o[2], hx, hz, wall.a, wall.b)
        closer = s < s_col
        s_col = np.where(closer, s, s_col)
        w_col[closer] = WALL0 + k
    with np.errstate(divide="ignore", invalid="ignore"):
        t_wall = (s_col[None, :] / ct[:, None]).astype(dtype)
    wall_first = t_wall < t_row[:, None]
    t = np.where(wall_first, t_wall, t_row[:, None].astype(dtype))
    sid = np.where(wall_first, w_col[None, :], sid_row[:, None]).astype(np.int32)
    for k in partial:
        wall = world.walls[k]
        s = _seg_dist_2d(o[0], o[2], hx, hz, wall.a, wall.b)
        cols = np.where(s < s_col)[0]
        if len(cols) == 0:
            continue
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            tw = s[None, cols] / ct[:, None]
            y = o[1] - tw * st[:, None]
        hit = (y >= wall.y_top) & (y <= wall.y_bottom) & (tw < t[:, cols])
        sub_t = t[:, cols]
        sub_s = sid[:, cols]
        sub_t[hit] = tw[hit]
        sub_s[hit] = WALL0 + k
        t[:, cols] = sub_t
        sid[:, cols] = sub_s
    t1 = time.perf_counter()
    axis = np.full((nr, nc), -1, dtype=np.int8)
    if boxes:
        base = box_id0(world)
        d3 = dirs.reshape(nr, nc, 3)
        h_cam = -o[1]
        for j, bx in enumerate(boxes):
            x0, z0, x1, z1 = bx.lo[0], bx.lo[2], bx.hi[0], bx.hi[2]
            foot = np.array([[x0, z0], [x1, z0], [x1, z1], [x0, z1]])
            lo_lon, hi_lon = _lon_interval(o[0], o[2], foot, rot, pad=1e-6)
            # Conservative latitude range from the nearest horizontal distance to the footprint.
            qx = np.clip(o[0], bx.lo[0], bx.hi[0])
            qz = np.clip(o[2], bx.lo[2], bx.hi[2])
            dmin = max(float(np.hypot(o[0] - qx, o[2] - qz)), 1e-6)
            top_above = -bx.lo[1] - h_cam  # box top height above the camera
            if top_above > 0:
                lat_hi = np.arctan2(top_above, dmin)
            else:  # the top's farthest point is at most dmin + the footprint's diagonal away
                lat_hi = np.arctan2(top_above, dmin + np.hypot(x1 - x0, z1 - z0))
            bottom_above = -bx.hi[1] - h_cam  # box bottom height above the camera (< 0 for furniture)
            if bottom_above <= 0:
                lat_lo = np.arctan2(bottom_above, dmin)
            else:  # a hanging box (a lamp): its bottom's farthest point is the lowest one
                lat_lo = np.arctan2(bottom_above, dmin + np.hypot(x1 - x0, z1 - z0))
            rows = np.where((lat >= lat_lo - 1e-9) & (lat <= lat_hi + 1e-9))[0]
            if len(rows) == 0:
                continue
            r0, r1 = rows[0], rows[-1] + 1
            for c0, c1 in _index_ranges(lon, lo_lon, hi_lon, periodic=True):
                dd = d3[r0:r1, c0:c1]
                with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
                    tn = tf = ax = None
                    for a in range(3):
                        inv = 1.0 / dd[..., a]
                        t_lo = (bx.lo[a] - o[a]) * inv
                        t_hi = (bx.hi[a] - o[a]) * inv
                        tmin = np.minimum(t_lo, t_hi)
                        tmax = np.maximum(t_lo, t_hi)
                        if tn is None:
                            tn, tf, ax = tmin, tmax, np.zeros(tmin.shape, dtype=np.int8)
                        else:
                            bigger = tmin > tn
                            tn = np.where(bigger, tmin, tn)
                            ax[bigger] = a
                            tf = np.minimum(tf, tmax)
                sub_t = t[r0:r1, c0:c1]
                hit = (tn <= tf) & (tn > EPS) & (tn < sub_t)
                sub_t[hit] = tn[hit]
                sid[r0:r1, c0:c1][hit] = base + j
                axis[r0:r1, c0:c1][hit] = ax[hit]
    t2 = time.perf_counter()
    if timings is not None:
        timings[shell_key] = timings.get(shell_key, 0.0) + (t1 - t0)
        if boxes:
            timings[box_key] = timings.get(box_key, 0.0) + (t2 - t1)
    return Hits(t=t.reshape(-1), sid=sid.reshape(-1), box_axis=axis.reshape(-1)), dirs
