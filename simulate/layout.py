"""Ground-truth layout of a view: per-column boundaries and HorizonNet corners.

The layout is that of the room SHELL (walls, floor, ceiling; furniture
ignored), as an Atlanta-world floor plan sees it: only full-height walls count.
For each image column, looking along its horizontal direction, d is the
horizontal distance to the first full-height wall; with camera height h and
ceiling height C: theta_floor = -atan2(h, d), theta_ceiling = atan2(C - h, d).
These are exactly the latitudes of the floor/wall and ceiling/wall depth
discontinuities of the empty room. Doorways (two-rooms preset): the opening
does not stop the ray, so through a doorway both boundaries lie on the next
room's far wall (the boundary the camera sees through the doorway), and the
lintel above the opening is ignored by the layout: in doorway columns the
pixels above the ceiling boundary show either ceiling or the lintel's face.

HorizonNet JSON ({"z0", "z1", "uv"}, as HorizonNet's inference.py writes it):
z0 = 50 (ceiling 50 units above the camera), z1 = -50 h / (C - h) (floor,
negative), uv = corners as image fractions u = col / W, v = row / H where
(col, row) are HorizonNet's pixel coordinates (pixel centres at integers, the
same as DESIGN.md's: col = (phi/2pi + 0.5) W - 0.5), one [u, v_ceiling] then
one [u, v_floor] per corner, corners sorted by u in [0, 1). The corners are
the vertices of the visibility polygon of the full-height walls: real room
corners, plus, where a wall corner (or a door jamb) occludes a farther wall,
the occluding corner and its shadow point on the far wall at the same u.
`representable` says the JSON reproduces the .npy boundary (checked to 1e-6
rad per column); `--with-layout` supplies the JSON when it does, else the .npy.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from panogeom.equirect import angles_to_pixel, column_longitudes, pixel_to_angles
from simulate.geometry import Camera, World

Z0 = 50.0


@dataclass
class ViewLayout:
    boundary: np.ndarray  # [2,W] float32 latitudes: row 0 ceiling (>0), row 1 floor (<0)
    horizonnet: dict  # {"z0","z1","uv"}
    representable: bool  # the JSON reproduces `boundary` exactly


def _segments(world: World) -> tuple[np.ndarray, np.ndarray]:
    """2D segments of the full-height walls (floor to ceiling)."""
    a, b = [], []
    for wall in world.walls:
        if wall.y_bottom >= 0.0 and wall.y_top <= world.ceiling_y:
            a.append(wall.a)
            b.append(wall.b)
    return np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)


def ray_segments(c: np.ndarray, d: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distances [R,S] along 2D rays c + t d (d [R,2] unit) to segments (a,b) [S,2]; inf when missed."""
    e = b - a  # [S,2]
    w = a - c  # [S,2]
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = d[:, None, 0] * e[None, :, 1] - d[:, None, 1] * e[None, :, 0]
        t = (w[None, :, 0] * e[None, :, 1] - w[None, :, 1] * e[None, :, 0]) / denom
        s = (w[None, :, 0] * d[:, None, 1] - w[None, :, 1] * d[:, None, 0]) / denom
    ok = np.isfinite(t) & (t > 1e-9) & (s >= -1e-9) & (s <= 1 + 1e-9)
    return np.where(ok, t, np.inf)


def _column_dirs(cam: Camera, lon: np.ndarray) -> np.ndarray:
    """World (x, z) unit directions of camera longitudes `lon`."""
    rot = cam.rotation
    dc = np.stack([np.sin(lon), np.zeros_like(lon), np.cos(lon)], axis=-1)
    dw = dc @ rot.T
    d2 = dw[:, [0, 2]]
    return d2 / np.linalg.norm(d2, axis=1, keepdims=True)


def _camera_lon(cam: Camera, xz: np.ndarray) -> np.ndarray:
    """Camera-frame longitude of world points (x, z) [N,2] seen from the camera."""
    rel = np.zeros((len(xz), 3))
    rel[:, 0] = xz[:, 0] - cam.position[0]
    rel[:, 2] = xz[:, 1] - cam.position[2]
    loc = rel @ cam.rotation  # world -> camera (R^T v)
    return np.arctan2(loc[:, 0], loc[:, 2])


def boundary(world: World, cam: Camera, width: int) -> np.ndarray:
    """[2, width] float64 ceiling and floor boundary latitudes at the column centres."""
    lon = column_longitudes(width)
    d = _column_dirs(cam, lon)
    c = cam.position[[0, 2]]
    dist = ray_segments(c, d, *_segments(world)).min(axis=1)
    h, ch = cam.height, world.ceiling_height
    return np.stack([np.arctan2(ch - h, dist), -np.arctan2(h, dist)])


def visibility_corners(world: World, cam: Camera) -> list[tuple[float, int, np.ndarray]]:
    """Corners of the visibility polygon of the full-height walls: (camera longitude, order
    among equal longitudes, world (x, z))."""
    a, b = _segments(world)
    c = cam.position[[0, 2]]
    verts = np.unique(np.round(np.concatenate([a, b]), 9), axis=0)
    pts: list[tuple[float, int, np.ndarray]] = []  # (lon, order key, point)
    for v in verts:
        dist = float(np.linalg.norm(v - c))
        dvec = (v - c) / dist
        hits = ray_segments(c, dvec[None], a, b)[0]
        if hits.min() < dist - 1e-7:
            continue  # hidden
        lon_v = float(_camera_lon(cam, v[None])[0])
        # Walls meeting at v: which side of the ray do their other ends lie on?
        inc = np.where((np.linalg.norm(a - v, axis=1) < 1e-7) | (np.linalg.norm(b - v, axis=1) < 1e-7))[0]
        others = [b[i] if np.linalg.norm(a[i] - v) < 1e-7 else a[i] for i in inc]
        sides = [dvec[0] * (o[1] - v[1]) - dvec[1] * (o[0] - v[0]) for o in others]
        if len(sides) >= 2 and min(sides) < -1e-9 and max(sides) > 1e-9:
            pts.append((lon_v, 0, v))
            continue
        # The ray grazes v and goes on: the occluded wall's shadow point at the same longitude.
        beyond = np.where(np.isfinite(hits) & (hits > dist + 1e-7), hits, np.inf)
        for i in inc:
            beyond[i] = np.inf
        far = float(beyond.min())
        if not np.isfinite(far):
            pts.append((lon_v, 0, v))
            continue
        shadow = c + dvec * far
        # Order by sweep: if v's walls are seen at smaller longitudes, the near corner comes first.
        o = others[0]
        probe = v + 1e-4 * (o - v) / np.linalg.norm(o - v)
        dlon = float(np.angle(np.exp(1j * (_camera_lon(cam, probe[None])[0] - lon_v))))
        if dlon < 0:
            pts.append((lon_v, 0, v))
            pts.append((lon_v, 1, shadow))
        else:
            pts.append((lon_v, 0, shadow))
            pts.append((lon_v, 1, v))
    return pts


def horizonnet_json(world: World, cam: Camera, height: int) -> dict:
    width = 2 * height
    h, ch = cam.height, world.ceiling_height
    c = cam.position[[0, 2]]
    corners = visibility_corners(world, cam)
    rows = []
    for lon_v, key, p in corners:
        dist = float(np.linalg.norm(p - c))
        col, r_c = angles_to_pixel(lon_v, np.arctan2(ch - h, dist), height, width)
        _, r_f = angles_to_pixel(lon_v, -np.arctan2(h, dist), height, width)
        u = (float(col) % width) / width
        rows.append((u, key, float(r_c) / height, float(r_f) / height))
    rows.sort(key=lambda r: (r[0], r[1]))
    uv = []
    for u, _, vc, vf in rows:
        uv.append([u, vc])
        uv.append([u, vf])
    return {"z0": Z0, "z1": -Z0 * h / (ch - h), "uv": uv}


def horizonnet_to_boundary(data: dict, height: int, width: int) -> np.ndarray:
    """Per-column [2, width] boundary latitudes from HorizonNet JSON corners (walls straight
    between consecutive corners, wrapping at the seam). Used by the tests; independent of World."""
    uv = np.asarray(data["uv"], dtype=np.float64).reshape(-1, 2, 2)
    z0, z1 = float(data["z0"]), float(data["z1"])
    lon, lat_c = pixel_to_angles(uv[:, 0, 0] * width, uv[:, 0, 1] * height, height, width)
    _, lat_f = pixel_to_angles(uv[:, 1, 0] * width, uv[:, 1, 1] * height, height, width)
    dist = -z1 / np.tan(-lat_f)  # horizontal distance of each corner, in HorizonNet units
    pts = np.stack([dist * np.sin(lon), dist * np.cos(lon)], axis=-1)  # camera-frame (x, z)
    a = pts
    b = np.roll(pts, -1, axis=0)
    keep = np.linalg.norm(b - a, axis=1) > 1e-9
    cols = column_longitudes(width)
    d = np.stack([np.sin(cols), np.cos(cols)], axis=-1)
    t = ray_segments(np.zeros(2), d, a[keep], b[keep]).min(axis=1)
    return np.stack([np.arctan2(z0, t), -np.arctan2(-z1, t)])


def view_layout(world: World, cam: Camera, height: int) -> ViewLayout:
    bnd = boundary(world, cam, 2 * height)
    hn = horizonnet_json(world, cam, height)
    rec = horizonnet_to_boundary(hn, height, 2 * height)
    representable = bool(np.all(np.isfinite(rec)) and np.abs(rec - bnd).max() < 1e-6)
    return ViewLayout(boundary=bnd.astype(np.float32), horizonnet=hn, representable=representable)
