"""Box sampling: the merged floor plan extruded from floor to ceiling, sampled into points.

Points are placed analytically on each plane (no mesh sampling), so they lie exactly on the
layout surfaces: a jittered (stratified) grid of `density` points per m^2 on every wall of the
union's boundary, and on the floor and ceiling polygons. Each point keeps its plane normal (into
the room); its colour comes from the nearest training panorama whose line of sight the layout
does not block. See docs/floorplan.md.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
import shapely
from shapely.geometry import Polygon
from shapely.geometry.polygon import orient

from floorplan.union import polygon_to_world, repair_polygon
from panogeom.equirect import project_to_pixels, sample_bilinear
from panogeom.surfaces import CEILING, FLOOR, WALL
from schemas.union import Room


@dataclass
class Samples:
    points: np.ndarray  # [N,3] float64 world
    normals: np.ndarray  # [N,3] unit, into the room
    surface: np.ndarray  # [N] int8: WALL / FLOOR / CEILING
    room: np.ndarray  # [N] int32 room index


def stratified_rect(
    length: float, height: float, density: float, rng: np.random.Generator | None
) -> np.ndarray:
    """[n,2] points (s, t) in [0,length] x [0,height], one per cell of a grid of ~density cells per m^2.

    The cell counts are chosen so that their product is the nearest whole number of
    points to area * density (the spacing along s is 1/sqrt(density), rounded to fit).
    """
    area = length * height
    if area <= 0:
        return np.zeros((0, 2))
    target = area * density
    spacing = 1.0 / np.sqrt(density)
    ns = max(1, round(length / spacing))
    nt = max(1, round(target / ns))
    if round(target) == 0:
        return np.zeros((0, 2))
    ii, jj = np.meshgrid(np.arange(ns), np.arange(nt), indexing="ij")
    off = rng.uniform(size=(ns * nt, 2)) if rng is not None else np.full((ns * nt, 2), 0.5)
    s = (ii.reshape(-1) + off[:, 0]) * (length / ns)
    t = (jj.reshape(-1) + off[:, 1]) * (height / nt)
    return np.stack([s, t], axis=1)


def stratified_polygon(poly: Polygon, density: float, rng: np.random.Generator | None) -> np.ndarray:
    """[n,2] points inside `poly` (holes excluded): a jittered square grid of spacing 1/sqrt(density)
    over its bounding box, kept where inside, so the expected count is area * density."""
    if poly.is_empty or poly.area <= 0:
        return np.zeros((0, 2))
    spacing = 1.0 / np.sqrt(density)
    x0, z0, x1, z1 = poly.bounds
    nx = max(1, int(np.ceil((x1 - x0) / spacing)))
    nz = max(1, int(np.ceil((z1 - z0) / spacing)))
    out = []
    rows_per_chunk = max(1, 2_000_000 // nx)  # bound memory on huge plans
    for r0 in range(0, nz, rows_per_chunk):
        jj, ii = np.meshgrid(np.arange(r0, min(nz, r0 + rows_per_chunk)), np.arange(nx), indexing="ij")
        n = jj.size
        off = rng.uniform(size=(n, 2)) if rng is not None else np.full((n, 2), 0.5)
        x = x0 + (ii.reshape(-1) + off[:, 0]) * spacing
        z = z0 + (jj.reshape(-1) + off[:, 1]) * spacing
        keep = shapely.contains_xy(poly, x, z)
        out.append(np.stack([x[keep], z[keep]], axis=1))
    return np.concatenate(out) if out else np.zeros((0, 2))


def room_walls(poly: Polygon) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Walls of a room as (a, b, inward normal) in (x, z): every edge of its outline and of its holes.

    Rings are oriented exterior counter-clockwise, holes clockwise (in (x, z)), so the
    room is always on the left of a -> b and the inward normal is (-dz, dx) / |b - a|.
    """
    poly = orient(poly, sign=1.0)
    walls = []
    for ring in [poly.exterior, *poly.interiors]:
        c = np.asarray(ring.coords, dtype=np.float64)
        for a, b in itertools.pairwise(c):
            d = b - a
            length = float(np.hypot(*d))
            if length < 1e-9:
                continue
            walls.append((a, b, np.array([-d[1], d[0]]) / length))
    return walls


def sample_rooms(
    rooms: list[Room],
    *,
    density: float,
    seed: int,
    jitter: bool,
    surfaces: tuple[str, ...],
) -> Samples:
    """Sample every room's walls, floor and ceiling at `density` points per m^2.

    Only the boundary of the merged floor plan is a wall: walls two views' rooms
    shared (a doorway) are interior to the union and get no points.
    """
    rng = np.random.default_rng(seed) if jitter else None
    pts, nrm, surf, rid = [], [], [], []

    def add(p, n, kind, i):
        pts.append(p)
        nrm.append(np.broadcast_to(n, p.shape))
        surf.append(np.full(len(p), kind, np.int8))
        rid.append(np.full(len(p), i, np.int32))

    for i, room in enumerate(rooms):
        poly = Polygon(room.polygon, room.holes)
        h = room.floor_y - room.ceiling_y
        if "wall" in surfaces:
            for a, b, n in room_walls(poly):
                length = float(np.hypot(*(b - a)))
                st = stratified_rect(length, h, density, rng)
                frac = st[:, :1] / length
                xz = a + frac * (b - a)
                p = np.stack([xz[:, 0], room.ceiling_y + st[:, 1], xz[:, 1]], axis=1)
                add(p, np.array([n[0], 0.0, n[1]]), WALL, i)
        for kind, name, y, n in (
            (FLOOR, "floor", room.floor_y, (0.0, -1.0, 0.0)),
            (CEILING, "ceiling", room.ceiling_y, (0.0, 1.0, 0.0)),
        ):
            if name not in surfaces:
                continue
            xz = stratified_polygon(poly, density, rng)
            p = np.stack([xz[:, 0], np.full(len(xz), y), xz[:, 1]], axis=1)
            add(p, np.asarray(n), kind, i)
    if not pts:
        z = np.zeros((0, 3))
        return Samples(z, z.copy(), np.zeros(0, np.int8), np.zeros(0, np.int32))
    return Samples(
        np.concatenate(pts),
        np.ascontiguousarray(np.concatenate(nrm)),
        np.concatenate(surf),
        np.concatenate(rid),
    )


def surface_areas(rooms: list[Room]) -> dict[str, float]:
    """Total wall / floor / ceiling area (m^2) of the extruded floor plan."""
    wall = floor = 0.0
    for room in rooms:
        poly = Polygon(room.polygon, room.holes)
        wall += poly.length * (room.floor_y - room.ceiling_y)  # .length counts hole rings too
        floor += poly.area
    return {"wall": wall, "floor": floor, "ceiling": floor}


def layout_edges(rooms: list[Room]) -> tuple[np.ndarray, np.ndarray]:
    """All wall segments (a, b) [E,2] in (x, z): the occluders of the line-of-sight test."""
    a, b = [], []
    for room in rooms:
        for wa, wb, _ in room_walls(Polygon(room.polygon, room.holes)):
            a.append(wa)
            b.append(wb)
    return np.asarray(a, dtype=np.float64).reshape(-1, 2), np.asarray(b, dtype=np.float64).reshape(-1, 2)


def _cross(o, p, q):
    return (p[..., 0] - o[..., 0]) * (q[..., 1] - o[..., 1]) - (p[..., 1] - o[..., 1]) * (
        q[..., 0] - o[..., 0]
    )


def line_of_sight(
    camera_xz: np.ndarray, targets_xz: np.ndarray, a: np.ndarray, b: np.ndarray, chunk: int = 8192
) -> np.ndarray:
    """[N] bool: the 2D segment camera -> target crosses none of the segments (a, b) (proper crossings).

    Walls span floor to ceiling, so in the extruded plan a 3D line of sight is
    blocked exactly when its projection on the x-z plane crosses a wall.
    """
    c = np.asarray(camera_xz, dtype=np.float64).reshape(1, 1, 2)
    out = np.ones(len(targets_xz), bool)
    if len(a) == 0:
        return out
    A, B = a[None], b[None]
    for s in range(0, len(targets_xz), chunk):
        p = targets_xz[s : s + chunk, None, :]
        d1 = _cross(A, B, c)  # camera side of each wall
        d2 = _cross(A, B, p)
        d3 = _cross(c, p, A)
        d4 = _cross(c, p, B)
        hit = (d1 * d2 < 0) & (d3 * d4 < 0)
        out[s : s + chunk] = ~hit.any(axis=1)
    return out


def choose_views(
    points: np.ndarray,
    normals: np.ndarray,
    centres: np.ndarray,
    rooms: list[Room],
    *,
    eps: float,
    view_regions: list | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Per point: index of the nearest camera centre [V,3] that sees it, and whether any does.

    A camera sees a point when the 2D segment between them crosses no wall of the
    merged plan and, where `view_regions` gives the camera's own floor polygon
    (world frame, None = unknown), the point lies inside it: the merged plan has no
    walls between rooms joined by a doorway, but each view's own layout stops at
    its room's walls. Tiers: both tests, else line of sight only, else the nearest
    camera (flagged False). Wall points sit on an occluder, so they are tested
    `eps` into the room along their normal.
    """
    a, b = layout_edges(rooms)
    target = points[:, [0, 2]] + eps * normals[:, [0, 2]]
    dist = np.linalg.norm(points[:, None, :] - centres[None, :, :], axis=2)  # [N,V]
    clear = np.stack([line_of_sight(c[[0, 2]], target, a, b) for c in centres], axis=1)
    if view_regions is not None:
        own = np.stack(
            [
                np.ones(len(points), bool)
                if r is None
                else shapely.contains_xy(r, target[:, 0], target[:, 1])
                for r in view_regions
            ],
            axis=1,
        )
    else:
        own = np.ones_like(clear)
    best = dist.argmin(axis=1)
    for ok in (clear, clear & own):  # later tiers override earlier ones where they apply
        masked = np.where(ok, dist, np.inf)
        has = ok.any(axis=1)
        best = np.where(has, masked.argmin(axis=1), best)
    return best, clear.any(axis=1)


def view_regions_from_layout(layout, views, margin: float) -> list:
    """Each train view's own floor polygon in the world (buffered by `margin`), or None without a layout."""
    have = {v.view: v for v in layout.views} if layout is not None else {}
    out = []
    for v in views:
        vl = have.get(v.name)
        if vl is None:
            out.append(None)
            continue
        poly, _ = repair_polygon(polygon_to_world(vl.floor_polygon, v.pose_matrix, vl.camera_height))
        out.append(None if poly.is_empty else poly.buffer(margin, join_style="mitre"))
    return out


def colour_points(
    points: np.ndarray, view_index: np.ndarray, poses: list[np.ndarray], images: list[np.ndarray]
) -> np.ndarray:
    """[N,3] colour of each point from its view's panorama at the point's projection."""
    colors = np.zeros((len(points), 3), np.float64)
    for v, (pose, img) in enumerate(zip(poses, images)):
        sel = np.nonzero(view_index == v)[0]
        if len(sel) == 0:
            continue
        col, row = project_to_pixels(points[sel], pose, img.shape[0], img.shape[1])
        colors[sel] = sample_bilinear(img, col, row)
    return colors


def room_mesh(rooms: list[Room]):
    """The extruded floor plan as one trimesh (faces wound so normals point into the rooms, like the cloud's)."""
    import trimesh

    meshes = []
    for room in rooms:
        poly = orient(Polygon(room.polygon, room.holes), sign=1.0)
        tris = [orient(t, sign=1.0) for t in shapely.constrained_delaunay_triangles(poly).geoms if t.area > 0]
        corners = np.array([np.asarray(t.exterior.coords)[:3] for t in tris])
        verts, inv = np.unique(corners.reshape(-1, 2).round(9), axis=0, return_inverse=True)
        m = trimesh.creation.extrude_triangulation(verts, inv.reshape(-1, 3), room.floor_y - room.ceiling_y)
        # Extrusion frame (a, b, c) -> world (x = a, y = floor_y - c, z = b): a proper rotation.
        t = np.array([[1, 0, 0, 0], [0, 0, -1, room.floor_y], [0, 1, 0, 0], [0, 0, 0, 1]], dtype=np.float64)
        m.apply_transform(t)
        m.invert()
        meshes.append(m)
    return trimesh.util.concatenate(meshes) if meshes else None
