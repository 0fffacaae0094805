"""Scene geometry of the simulator: Atlanta-world rooms, cameras, lights.

World frame (DESIGN.md): OpenCV axes, y down (gravity +y). The floor is the
plane y = 0, the ceiling y = -ceiling_height. Floor plans live in the world
(x, z) plane; polygons are stored counter-clockwise in (x, z), i.e. with a
positive shoelace area when x is the first and z the second coordinate (seen
from above, looking along +y, with +x to the right, +z points up the page, so
this is also counter-clockwise "looking down from above").

Walls have zero thickness. A wall is a vertical quad: a 2D segment (a, b) in
(x, z), spanning world y from `y_top` (<= 0, more negative = higher) to
`y_bottom`. A doorway cuts an opening from the floor up to `top_y` into a
shared wall, leaving a lintel above it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from shapely.geometry import Point, Polygon, box
from shapely.geometry.polygon import orient
from shapely.ops import unary_union

__all__ = [
    "Room",
    "Wall",
    "Doorway",
    "Box",
    "Light",
    "Camera",
    "World",
    "yaw_pose",
    "build_world",
    "place_cameras",
    "PRESET_NAMES",
]

PRESET_NAMES = ("cuboid", "l-shape", "two-rooms", "demo", "suite")

LIGHT_DROP = 0.45  # lamps hang this far below the ceiling (m)
WALL_MARGIN = 0.5  # cameras keep this far from walls (m)
FURNITURE_CAMERA_CLEARANCE = 0.4  # furniture footprints keep this far from cameras (m)


@dataclass
class Room:
    name: str
    polygon: np.ndarray  # [K,2] (x,z), CCW
    rects: list[tuple[float, float, float, float]]  # convex parts (x0, z0, x1, z1) whose union is the room

    @property
    def shape(self) -> Polygon:
        return Polygon(self.polygon)


@dataclass
class Wall:
    a: np.ndarray  # (x,z)
    b: np.ndarray  # (x,z)
    y_top: float  # world y of the top edge (<= bottom)
    y_bottom: float
    material: str = "paint"
    kind: str = "wall"  # "wall" or "lintel"

    @property
    def length(self) -> float:
        return float(np.hypot(*(self.b - self.a)))


@dataclass
class Doorway:
    a: np.ndarray
    b: np.ndarray
    rooms: tuple[int, int]
    top_y: float  # world y of the opening's top (negative)


@dataclass
class Box:
    kind: str
    lo: np.ndarray  # [3] world min corner
    hi: np.ndarray  # [3] world max corner (hi[1] == 0: stands on the floor)
    color: np.ndarray  # [3] RGB albedo in [0,1]
    material: str = "wood"


@dataclass
class Light:
    position: np.ndarray  # [3]
    intensity: float
    room: int


@dataclass
class Camera:
    name: str
    split: str
    position: np.ndarray  # [3] world, y = -height
    height: float
    yaw: float  # radians, rotation about world +y

    @property
    def pose(self) -> np.ndarray:
        return yaw_pose(self.yaw, self.position)

    @property
    def rotation(self) -> np.ndarray:
        return self.pose[:3, :3]


@dataclass
class World:
    preset: str
    rooms: list[Room]
    ceiling_height: float
    walls: list[Wall]
    doorways: list[Doorway]
    lights: list[Light]
    floor_material: str
    outline: np.ndarray  # [K,2] CCW union of the rooms
    boxes: list[Box] = field(default_factory=list)
    #: the `plain-floor` effect: the floor keeps its material's flat colour, untextured, without detail
    floor_plain: bool = False
    # Convex parts of the free space where cameras may stand, one list per room.
    camera_regions: list[list[tuple[float, float, float, float]]] = field(default_factory=list)

    @property
    def ceiling_y(self) -> float:
        return -self.ceiling_height

    @property
    def union_shape(self) -> Polygon:
        return Polygon(self.outline)

    def room_of(self, xz: np.ndarray) -> int:
        p = Point(float(xz[0]), float(xz[1]))
        for i, r in enumerate(self.rooms):
            if r.shape.buffer(1e-9).contains(p):
                return i
        return -1


def yaw_pose(yaw: float, position: np.ndarray) -> np.ndarray:
    """Camera-to-world 4x4 of a level camera turned by `yaw` about world +y."""
    c, s = np.cos(yaw), np.sin(yaw)
    pose = np.eye(4)
    pose[:3, :3] = [[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]
    pose[:3, 3] = position
    return pose


# ----------------------------------------------------------------------------- rooms


def _ccw(poly: np.ndarray) -> np.ndarray:
    poly = np.asarray(poly, dtype=np.float64)
    x, z = poly[:, 0], poly[:, 1]
    area = 0.5 * np.sum(x * np.roll(z, -1) - np.roll(x, -1) * z)
    return poly if area > 0 else poly[::-1].copy()


def _drop_collinear(poly: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    keep = []
    n = len(poly)
    for i in range(n):
        p0, p1, p2 = poly[i - 1], poly[i], poly[(i + 1) % n]
        cross = (p1[0] - p0[0]) * (p2[1] - p1[1]) - (p1[1] - p0[1]) * (p2[0] - p1[0])
        if abs(cross) > tol:
            keep.append(p1)
    return np.asarray(keep)


def _rect_poly(x0: float, z0: float, x1: float, z1: float) -> np.ndarray:
    return np.array([[x0, z0], [x1, z0], [x1, z1], [x0, z1]], dtype=np.float64)


def _outline(rects: list[tuple[float, float, float, float]]) -> np.ndarray:
    shape = orient(unary_union([box(*r) for r in rects]), sign=1.0)
    pts = np.asarray(shape.exterior.coords)[:-1]
    return _ccw(_drop_collinear(pts))


def _polygon_edges(poly: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    return [(poly[i].copy(), poly[(i + 1) % len(poly)].copy()) for i in range(len(poly))]


def _round(v: float) -> float:
    # Millimetre-round the room dimensions so floor plans print cleanly.
    return float(np.round(v, 3))


def build_world(preset: str, rng: np.random.Generator) -> World:
    """The room shell, doorways, lights and wall materials of a preset (no furniture, no cameras)."""
    if preset not in PRESET_NAMES:
        raise ValueError(f"unknown preset {preset!r}; choose one of {', '.join(PRESET_NAMES)}")
    ceiling = _round(rng.uniform(2.4, 3.2))
    doorways: list[Doorway] = []
    if preset == "cuboid":
        w, d = _round(rng.uniform(4.0, 6.0)), _round(rng.uniform(3.5, 5.0))
        rects = [(-w / 2, -d / 2, w / 2, d / 2)]
        rooms = [Room("room", _rect_poly(*rects[0]), rects)]
        camera_regions = [rects]
    elif preset in ("l-shape", "demo"):
        if preset == "demo":
            ceiling = _round(rng.uniform(2.6, 2.8))
            w, d = _round(rng.uniform(5.6, 6.0)), _round(rng.uniform(5.2, 5.6))
            cw, cd = _round(w * 0.42), _round(d * 0.42)
        else:
            w, d = _round(rng.uniform(5.0, 7.0)), _round(rng.uniform(5.0, 7.0))
            cw, cd = _round(w * rng.uniform(0.35, 0.5)), _round(d * rng.uniform(0.35, 0.5))
        x0, z0 = -w / 2, -d / 2
        rects = [(x0, z0, x0 + w, z0 + d - cd), (x0, z0, x0 + w - cw, z0 + d)]
        rooms = [Room("room", _outline(rects), rects)]
        if preset == "demo":
            # The elbow (intersection of both arms) sees the whole room.
            camera_regions = [[(x0, z0, x0 + w - cw, z0 + d - cd)]]
        else:
            camera_regions = [rects]
    elif preset == "suite":
        rooms, rects, doorways = _suite(rng, ceiling)
        camera_regions = [[r] for r in rects]
    else:  # two-rooms
        wa, da = _round(rng.uniform(3.5, 5.0)), _round(rng.uniform(3.5, 5.0))
        wb, db = _round(rng.uniform(3.0, 4.5)), _round(rng.uniform(3.0, 4.5))
        # Room B sits to the +x side of A, its z range overlapping A's by >= 2 m.
        lo = max(-db + 2.0, -1.0)
        hi = min(da - 2.0, 1.0)
        zb0 = _round(rng.uniform(lo, hi)) if hi > lo else 0.0
        ra = (0.0, 0.0, wa, da)
        rb = (wa, zb0, wa + wb, zb0 + db)
        sx, sz = (wa + wb) / 2, da / 2
        ra = (ra[0] - sx, ra[1] - sz, ra[2] - sx, ra[3] - sz)
        rb = (rb[0] - sx, rb[1] - sz, rb[2] - sx, rb[3] - sz)
        rooms = [Room("room_a", _rect_poly(*ra), [ra]), Room("room_b", _rect_poly(*rb), [rb])]
        shared_z0, shared_z1 = max(ra[1], rb[1]), min(ra[3], rb[3])
        door_w = _round(rng.uniform(0.9, 1.1))
        dz0 = _round(rng.uniform(shared_z0 + 0.3, shared_z1 - 0.3 - door_w))
        door_top = -_round(rng.uniform(2.0, min(2.2, ceiling - 0.25)))
        xw = ra[2]
        doorways = [Doorway(np.array([xw, dz0]), np.array([xw, dz0 + door_w]), (0, 1), door_top)]
        rects = [ra, rb]
        camera_regions = [[ra], [rb]]

    outline = _outline(rects)
    walls: list[Wall] = []
    cy = -ceiling
    for a, b in _polygon_edges(outline):
        walls.append(Wall(a, b, cy, 0.0))
    for dw in doorways:
        # The shared wall: the part of the boundary between both rooms, minus the opening.
        ra, rb = rooms[dw.rooms[0]].rects[0], rooms[dw.rooms[1]].rects[0]
        xw = dw.a[0]
        z0, z1 = max(ra[1], rb[1]), min(ra[3], rb[3])
        if dw.a[1] > z0:
            walls.append(Wall(np.array([xw, z0]), dw.a.copy(), cy, 0.0))
        if dw.b[1] < z1:
            walls.append(Wall(dw.b.copy(), np.array([xw, z1]), cy, 0.0))
        walls.append(Wall(dw.a.copy(), dw.b.copy(), cy, dw.top_y, kind="lintel"))

    # Materials: alternate patterned wallpaper and plain (texture-less) paint.
    start = int(rng.integers(0, 2))
    for i, wall in enumerate(walls):
        if wall.kind == "lintel":
            wall.material = "paint"
        else:
            wall.material = "wallpaper" if (i + start) % 2 == 0 else "paint"
    if preset == "suite":
        # real rooms: mostly painted walls, a third of them bare (no fine detail: nothing to match)
        for i, wall in enumerate(walls):
            if wall.kind == "wall":
                wall.material = ("wallpaper", "paint", "bare")[(i + start) % 3]
    if preset == "demo":
        floor_material = "wood"
    else:
        floor_material = "wood" if rng.uniform() < 0.5 else "carpet"

    lights: list[Light] = []
    for ri, room in enumerate(rooms):
        for r in room.rects:
            cx, cz = (r[0] + r[2]) / 2, (r[1] + r[3]) / 2
            lights.append(Light(np.array([cx, cy + LIGHT_DROP, cz]), 1.0, ri))
    return World(
        preset=preset,
        rooms=rooms,
        ceiling_height=ceiling,
        walls=walls,
        doorways=doorways,
        lights=lights,
        floor_material=floor_material,
        outline=outline,
        camera_regions=camera_regions,
    )


def _suite(rng: np.random.Generator, ceiling: float):
    """Three rooms in a row along +x (a living room, a dining room, a kitchen), each joined to the
    next by an opening 1.0-1.6 m wide: a real-estate capture's open plan, seen from room to room
    only through the openings."""
    widths = [_round(rng.uniform(4.0, 5.5)), _round(rng.uniform(3.5, 4.5)), _round(rng.uniform(3.0, 4.5))]
    depths = [_round(rng.uniform(3.5, 5.0)), _round(rng.uniform(3.5, 4.5)), _round(rng.uniform(3.0, 4.5))]
    rects = []
    x, z0 = 0.0, 0.0
    for k, (w, d) in enumerate(zip(widths, depths)):
        if k:  # overlap the previous room's z range by at least 2.5 m
            pz0, pz1 = rects[-1][1], rects[-1][3]
            lo, hi = pz0 + 2.5 - d, pz1 - 2.5
            z0 = _round(rng.uniform(lo, hi)) if hi > lo else pz0
        rects.append((x, z0, x + w, z0 + d))
        x += w
    zs = [r[1] for r in rects] + [r[3] for r in rects]
    sx, sz = x / 2, (min(zs) + max(zs)) / 2
    rects = [(r[0] - sx, r[1] - sz, r[2] - sx, r[3] - sz) for r in rects]
    names = ("living", "dining", "kitchen")
    rooms = [Room(n, _rect_poly(*r), [r]) for n, r in zip(names, rects)]
    doorways = []
    for k in range(2):
        ra, rb = rects[k], rects[k + 1]
        shared_z0, shared_z1 = max(ra[1], rb[1]), min(ra[3], rb[3])
        width = _round(rng.uniform(1.0, 1.6))
        dz0 = _round(rng.uniform(shared_z0 + 0.3, max(shared_z0 + 0.3, shared_z1 - 0.3 - width)))
        top = -_round(rng.uniform(2.0, min(2.2, ceiling - 0.25)))
        doorways.append(Doorway(np.array([ra[2], dz0]), np.array([ra[2], dz0 + width]), (k, k + 1), top))
    return rooms, rects, doorways


# ----------------------------------------------------------------------------- cameras


def _sample_in_rects(rng, rects, n, margin):
    rs = [(r[0] + margin, r[1] + margin, r[2] - margin, r[3] - margin) for r in rects]
    rs = [r for r in rs if r[2] > r[0] and r[3] > r[1]]
    areas = np.array([(r[2] - r[0]) * (r[3] - r[1]) for r in rs])
    idx = rng.choice(len(rs), size=n, p=areas / areas.sum())
    u = rng.uniform(size=(n, 2))
    out = np.empty((n, 2))
    for k, i in enumerate(idx):
        r = rs[i]
        out[k] = (r[0] + u[k, 0] * (r[2] - r[0]), r[1] + u[k, 1] * (r[3] - r[1]))
    return out


def _farthest_points(cands: np.ndarray, k: int, rng) -> list[int]:
    chosen = [int(rng.integers(len(cands)))]
    d = np.linalg.norm(cands - cands[chosen[0]], axis=1)
    for _ in range(k - 1):
        i = int(np.argmax(d))
        chosen.append(i)
        d = np.minimum(d, np.linalg.norm(cands - cands[i], axis=1))
    return chosen


def _in_hull(p: np.ndarray, pts: np.ndarray) -> bool:
    if len(pts) < 3:
        return True
    from shapely.geometry import MultiPoint

    hull = MultiPoint([tuple(q) for q in pts]).convex_hull
    if hull.area < 1e-6:
        return True
    return bool(hull.buffer(1e-9).contains(Point(*p)))


def _walk(world: World, n: int, rng: np.random.Generator) -> np.ndarray:
    """[n,2] train positions along a walk through the rooms (room centres and doorway centres
    joined), evenly spaced with a little sideways jitter: each panorama overlaps its neighbours
    on the walk most, the far ones little or not at all (a chain)."""
    stops = [np.mean(np.array(world.camera_regions[0][0]).reshape(2, 2), axis=0)]
    for k, dw in enumerate(world.doorways):
        stops.append((dw.a + dw.b) / 2)
        stops.append(np.mean(np.array(world.camera_regions[k + 1][0]).reshape(2, 2), axis=0))
    stops = np.array(stops)
    seg = np.linalg.norm(np.diff(stops, axis=0), axis=1)
    along = np.concatenate([[0.0], np.cumsum(seg)])
    out = np.zeros((n, 2))
    for i, s in enumerate(np.linspace(0.0, along[-1], n)):
        k = min(int(np.searchsorted(along, s, side="right")) - 1, len(seg) - 1)
        p = stops[k] + (s - along[k]) / seg[k] * (stops[k + 1] - stops[k])
        p = p + rng.uniform(-0.35, 0.35, 2)
        for dw in world.doorways:  # keep clear of the wall planes at the openings
            if abs(p[0] - dw.a[0]) < 0.4:
                p[0] = dw.a[0] + (0.4 if p[0] >= dw.a[0] else -0.4)
                p[1] = np.clip(p[1], min(dw.a[1], dw.b[1]) - 0.3, max(dw.a[1], dw.b[1]) + 0.3)
        out[i] = p
    return out


#: Test placements: "near" each train camera (0.35-1 m, inside their hull: interpolation), or
#: "away" from all of them (>= AWAY_MIN_DISTANCE m, anywhere in the free space: novel views as a
#: walk-through of a sparse capture sees them).
TEST_PLACEMENTS = ("near", "away")
AWAY_MIN_DISTANCE = 1.0


def _away_from(rng, rects, train_xz: np.ndarray, n: int, margin: float) -> np.ndarray:
    """`n` points of the free space (rooms' `rects`), each >= AWAY_MIN_DISTANCE m from every train camera
    (relaxed when the space is too small) and spread out (farthest-point order among the candidates)."""
    cands = _sample_in_rects(rng, rects, 2000, margin)
    dtrain = np.linalg.norm(cands[:, None, :] - train_xz[None], axis=2).min(axis=1)
    for lim in (AWAY_MIN_DISTANCE, 0.6, 0.3, 0.0):
        pool = cands[dtrain >= lim]
        if len(pool) >= n:
            break
    if n == 0:
        return np.zeros((0, 2))
    return pool[_farthest_points(pool, n, rng)]


def place_cameras(world: World, n_train: int, n_test: int, rng: np.random.Generator,
                  walk: bool = False, tripod_height: float | None = None,
                  test_placement: str = "near") -> list[Camera]:
    """Train cameras spread over the free space (or, with `walk`, along a walk through the rooms,
    for presets with doorways); test cameras near them, inside their hull when possible
    (`test_placement` "near"), or anywhere at least AWAY_MIN_DISTANCE m from every train camera
    ("away"). With `tripod_height` every camera stands that high (a capture from one tripod), else
    1.2-1.7 m."""
    if test_placement not in TEST_PLACEMENTS:
        raise ValueError(f"unknown test placement {test_placement!r}; choose one of {', '.join(TEST_PLACEMENTS)}")
    regions = world.camera_regions
    margin = WALL_MARGIN
    if walk and not world.doorways:
        raise ValueError("a walk needs rooms joined by doorways (presets two-rooms, suite)")
    # Train: farthest-point sampling per room, rooms taken round robin.
    per_room = [[] for _ in regions]
    for i in range(n_train):
        per_room[i % len(regions)].append(i)
    train_xz = np.zeros((n_train, 2))
    for ri, idxs in enumerate([] if walk else per_room):
        if not idxs:
            continue
        cands = _sample_in_rects(rng, regions[ri], 400, margin)
        if world.preset == "demo":
            # Keep the demo's train cameras close together (test views must be near them).
            centre = cands.mean(axis=0)
            cands = cands[np.linalg.norm(cands - centre, axis=1) < 0.9]
        sel = _farthest_points(cands, len(idxs), rng)
        for j, s in zip(idxs, sel):
            train_xz[j] = cands[s]
    if walk:
        train_xz = _walk(world, n_train, rng)
    # Test: near a train camera (0.35..1.0 m), at least 0.3 m from every train camera,
    # inside the train cameras' convex hull when there is one.
    test_xz = np.zeros((n_test, 2))
    room_of_train = [i % len(regions) for i in range(n_train)]
    if test_placement == "away":
        test_xz = _away_from(rng, [r for rs in regions for r in rs], train_xz, n_test, margin)
    for t in range(n_test if test_placement == "near" else 0):
        k = t % n_train
        ri = room_of_train[k]
        cands = _sample_in_rects(rng, regions[ri], 600, margin)
        dk = np.linalg.norm(cands - train_xz[k], axis=1)
        dall = np.linalg.norm(cands[:, None, :] - train_xz[None], axis=2).min(axis=1)
        dtest = (
            np.linalg.norm(cands[:, None, :] - test_xz[None, :t], axis=2).min(axis=1)
            if t
            else np.full(len(cands), np.inf)
        )
        ok = (dk <= 1.0) & (dall >= 0.3) & (dtest >= 0.3)
        hull_ok = np.array([_in_hull(c, train_xz) for c in cands[ok]], dtype=bool)
        pool = cands[ok][hull_ok] if hull_ok.any() else cands[ok]
        if len(pool) == 0:
            pool = cands[(dall >= 0.3) & (dtest >= 0.3)]
        if len(pool) == 0:
            pool = cands
        # Prefer close to train camera k, with a little randomness.
        score = np.linalg.norm(pool - train_xz[k], axis=1) - rng.uniform(0, 0.3, len(pool))
        test_xz[t] = pool[np.argmin(score)]
    cams: list[Camera] = []
    lo_h, hi_h = (1.35, 1.6) if world.preset == "demo" else (1.2, 1.7)
    for split, xz in (("train", train_xz), ("test", test_xz)):
        for i, p in enumerate(xz):
            h = float(np.round(rng.uniform(lo_h, hi_h), 4))
            if tripod_height is not None:
                h = float(tripod_height)
            yaw = float(rng.uniform(-np.pi, np.pi))
            pos = np.array([p[0], -h, p[1]])
            cams.append(Camera(f"{split}_{i:02d}", split, pos, h, yaw))
    return cams
