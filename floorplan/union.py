"""The per-view floor plans moved into the world frame and merged into one floor plan.

Each view's floor polygon (camera frame, (x, z) metres, floor at camera y = +camera_height) is
mapped through its camera-to-world pose onto the world x-z plane, repaired if invalid, and merged
with shapely's `unary_union`. Narrow gaps and slivers below the tolerance are closed by a
morphological closing then opening (mitre buffers keep square corners square). Rooms are the
connected components of the result; each gets the robust mean of its views' floor and ceiling
heights. See docs/floorplan.md.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import shapely
from shapely.geometry import GeometryCollection, MultiPolygon, Point, Polygon
from shapely.geometry.polygon import orient
from shapely.ops import unary_union

from runfs.errors import PanoError
from schemas.layout import ViewLayout
from schemas.union import Room


def polygon_to_world(polygon_xz, pose: np.ndarray, camera_height: float) -> np.ndarray:
    """A camera-frame floor polygon [K,2] (x, z) -> world (x, z) [K,2] through the camera-to-world pose.

    The polygon lies on the floor plane, camera y = +camera_height; each vertex
    (x, h, z) is mapped by R, t and the world y is dropped (exact for a level
    camera, i.e. R a rotation about y).
    """
    p = np.asarray(polygon_xz, dtype=np.float64).reshape(-1, 2)
    pose = np.asarray(pose, dtype=np.float64)
    cam = np.stack([p[:, 0], np.full(len(p), float(camera_height)), p[:, 1]], axis=1)
    world = cam @ pose[:3, :3].T + pose[:3, 3]
    return world[:, [0, 2]]


def camera_tilt_deg(pose: np.ndarray) -> float:
    """Angle between the camera's down axis (its +y) and world +y, degrees."""
    down = np.asarray(pose, dtype=np.float64)[:3, 1]
    return float(np.degrees(np.arccos(np.clip(down[1] / np.linalg.norm(down), -1.0, 1.0))))


def _polygonal_parts(geom) -> list[Polygon]:
    if geom is None or geom.is_empty:
        return []
    if isinstance(geom, Polygon):
        return [geom]
    if isinstance(geom, (MultiPolygon, GeometryCollection)):
        return [p for g in geom.geoms for p in _polygonal_parts(g)]
    return []  # points / lines left over by make_valid carry no area


def repair_polygon(poly) -> tuple[Polygon | MultiPolygon, bool]:
    """A valid polygonal geometry for `poly` (a shapely geometry or [K,2] vertices) and whether it was repaired.

    Self-intersections (a bow-tie) are split into their valid pieces by
    `make_valid`; if that leaves no area (degenerate rings) `buffer(0)` is tried.
    """
    if not isinstance(poly, (Polygon, MultiPolygon)):
        pts = np.asarray(poly, dtype=np.float64).reshape(-1, 2)
        if len(pts) < 3 or not np.all(np.isfinite(pts)):
            return Polygon(), True
        poly = Polygon(pts)
    if poly.is_valid:
        return poly, False
    parts = _polygonal_parts(shapely.make_valid(poly))
    if not parts:
        parts = _polygonal_parts(poly.buffer(0))
    fixed = unary_union(parts) if parts else Polygon()
    return fixed, True


def close_and_open(geom, tol: float):
    """Morphological closing (fills gaps < 2 tol) then opening (removes slivers < 2 tol)."""
    if tol <= 0 or geom.is_empty:
        return geom
    kw = {"join_style": "mitre", "mitre_limit": 10.0}
    closed = geom.buffer(tol, **kw).buffer(-tol, **kw)
    opened = closed.buffer(-tol, **kw).buffer(tol, **kw)
    return opened if not opened.is_empty else closed


def merge_floor_plans(polygons: list, *, tolerance: float, min_area: float, simplify: float) -> list[Polygon]:
    """Union of world-frame polygons -> its connected components (CCW exteriors, CW holes), largest first."""
    parts = [p for p in polygons if p is not None and not p.is_empty]
    if not parts:
        return []
    merged = close_and_open(unary_union(parts), tolerance)
    if simplify > 0:
        merged = merged.simplify(simplify, preserve_topology=True)
    rooms = [orient(p, sign=1.0) for p in _polygonal_parts(merged) if p.area >= min_area]
    # Holes that closing left narrower than the tolerance are noise too.
    cleaned = []
    for r in rooms:
        holes = [h for h in r.interiors if Polygon(h).area >= max(min_area * 0.1, tolerance**2 * 4)]
        cleaned.append(orient(Polygon(r.exterior, holes), sign=1.0))
    return sorted(cleaned, key=lambda p: -p.area)


def robust_mean(values, floor: float = 0.01) -> float:
    """Mean of the values within 3 scaled MADs (at least `floor`) of the median."""
    v = np.asarray(values, dtype=np.float64)
    if v.size == 0:
        raise ValueError("robust_mean of no values")
    med = np.median(v)
    mad = 1.4826 * np.median(np.abs(v - med))
    keep = np.abs(v - med) <= max(3.0 * mad, floor)
    return float(v[keep].mean())


def polygon_iou(a, b) -> float:
    inter = a.intersection(b).area
    uni = a.union(b).area
    return float(inter / uni) if uni > 0 else 0.0


def _ring(coords) -> list[tuple[float, float]]:
    return [(float(x), float(z)) for x, z in list(coords)[:-1]]


def assign_rooms(rooms: list[Polygon], positions_xz: dict[str, np.ndarray], view_polys: dict[str, object]):
    """View -> room index: the room holding the camera, else the one its floor polygon overlaps most."""
    out: dict[str, int] = {}
    for name, xz in positions_xz.items():
        pt = Point(float(xz[0]), float(xz[1]))
        idx = next((i for i, r in enumerate(rooms) if r.buffer(1e-6).contains(pt)), None)
        if idx is None:
            poly = view_polys.get(name)
            overlaps = [
                r.intersection(poly).area if poly is not None and not poly.is_empty else 0.0 for r in rooms
            ]
            if overlaps and max(overlaps) > 0:
                idx = int(np.argmax(overlaps))
        if idx is not None:
            out[name] = idx
    return out


def build_floor_plan(
    layouts: list[ViewLayout], poses: dict[str, np.ndarray], *, tolerance: float, min_room_area: float,
    simplify: float, max_tilt_deg: float, warn=lambda m: None
) -> tuple[list[Room], dict]:
    """Rooms and the per-view record for floor_plan.json (pure; no files). The settings are the
    union stage's (docs/floorplan.md)."""
    per_view: dict[str, dict] = {}
    world_polys: dict[str, object] = {}
    positions: dict[str, np.ndarray] = {}
    for vl in layouts:
        pose = poses[vl.view]
        tilt = camera_tilt_deg(pose)
        if tilt > max_tilt_deg:
            warn(f"view {vl.view}: camera tilted {tilt:.1f} deg from level; its floor plan is projected")
        w = polygon_to_world(vl.floor_polygon, pose, vl.camera_height)
        poly, repaired = repair_polygon(w)
        if repaired:
            warn(f"view {vl.view}: invalid floor polygon repaired (area {poly.area:.2f} m^2)")
        if poly.is_empty:
            warn(f"view {vl.view}: floor polygon has no area; ignored")
        elif not poly.buffer(tolerance).contains(Point(float(pose[0, 3]), float(pose[2, 3]))):
            # A layout always surrounds its own camera: this points at a frame or sign mix-up.
            warn(f"view {vl.view}: the camera lies outside its own floor polygon")
        cam_y = float(pose[1, 3])
        positions[vl.view] = pose[[0, 2], 3]
        world_polys[vl.view] = poly
        per_view[vl.view] = {
            "polygon_camera": [list(map(float, p)) for p in vl.floor_polygon],
            "polygon_world": [list(map(float, p)) for p in w],
            "repaired": repaired,
            "area_m2": float(poly.area),
            "position": [float(v) for v in pose[:3, 3]],
            "forward": [float(pose[0, 2]), float(pose[2, 2])],
            "floor_y": cam_y + float(vl.camera_height),
            "ceiling_y": cam_y - float(vl.ceiling_distance),
            "camera_height": float(vl.camera_height),
            "ceiling_distance": float(vl.ceiling_distance),
        }

    shapes = merge_floor_plans(list(world_polys.values()), tolerance=tolerance, min_area=min_room_area,
                               simplify=simplify)
    if not shapes:
        raise PanoError(
            "layout", "the views' floor polygons merge into nothing (all empty or below min_room_area)"
        )
    owner = assign_rooms(shapes, positions, world_polys)
    rooms: list[Room] = []
    for i, shape in enumerate(shapes):
        names = [n for n, r in owner.items() if r == i]
        if not names:
            warn(f"room {i} ({shape.area:.1f} m^2) holds no camera; heights from all views")
            names_h = list(per_view)
        else:
            names_h = names
        floors = [per_view[n]["floor_y"] for n in names_h]
        ceils = [per_view[n]["ceiling_y"] for n in names_h]
        if np.ptp(floors) > 0.1 or np.ptp(ceils) > 0.1:
            warn(
                f"room {i}: views disagree on heights (floor spread {np.ptp(floors):.2f} m, "
                f"ceiling spread {np.ptp(ceils):.2f} m); using their robust mean"
            )
        floor_y, ceiling_y = robust_mean(floors), robust_mean(ceils)
        if not ceiling_y < floor_y:
            raise PanoError(
                "layout", f"room {i}: ceiling (y={ceiling_y:.3f}) is not above the floor (y={floor_y:.3f})"
            )
        rooms.append(
            Room(
                polygon=_ring(shape.exterior.coords),
                holes=[_ring(h.coords) for h in shape.interiors],
                floor_y=floor_y,
                ceiling_y=ceiling_y,
                views=sorted(names),
            )
        )
        for n in names:
            per_view[n]["room"] = i
    return rooms, per_view


def room_shape(room: Room) -> Polygon:
    return Polygon(room.polygon, room.holes)


def draw_floor_plan(path: Path, rooms: list[Room], per_view: dict, dpi: int = 120) -> None:
    """floor_plan.png: rooms filled, per-view polygons dashed, cameras as dots with names (x right, z up)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import PathPatch
    from matplotlib.path import Path as MPath

    fig, ax = plt.subplots(figsize=(7, 7))
    colors = plt.get_cmap("tab10")
    for i, room in enumerate(rooms):
        rings = [np.asarray(room.polygon)] + [np.asarray(h) for h in room.holes]
        verts = np.concatenate([np.vstack([r, r[:1]]) for r in rings])
        codes = np.concatenate(
            [[MPath.MOVETO] + [MPath.LINETO] * (len(r) - 1) + [MPath.CLOSEPOLY] for r in rings]
        )
        ax.add_patch(
            PathPatch(MPath(verts, codes), facecolor=colors(i % 10), alpha=0.25, edgecolor="k", lw=2)
        )
        c = room_shape(room).representative_point()
        ax.text(
            c.x,
            c.y,
            f"room {i}\nfloor y={room.floor_y:.2f}\nceil y={room.ceiling_y:.2f}",
            ha="center",
            va="center",
            fontsize=8,
            color="0.2",
        )
    for name, rec in per_view.items():
        w = np.asarray(rec["polygon_world"])
        if len(w) >= 2:
            ax.plot(*np.vstack([w, w[:1]]).T, "--", lw=0.8, color=colors(rec.get("room", 0) % 10))
        x, _, z = rec["position"]
        ax.plot(x, z, "o", color="k", ms=5)
        fwd = rec.get("forward")
        if fwd is not None:  # the panorama's centre column looks this way
            ax.annotate(
                "", (x + 0.4 * fwd[0], z + 0.4 * fwd[1]), (x, z), arrowprops={"arrowstyle": "->", "lw": 0.8}
            )
        ax.annotate(name, (x, z), textcoords="offset points", xytext=(4, 4), fontsize=8)
    ax.set_aspect("equal")
    ax.autoscale_view()
    ax.set_xlabel("world x (m)")
    ax.set_ylabel("world z (m)")
    ax.set_title("floor plan (seen from above, y down)")
    ax.grid(True, lw=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
