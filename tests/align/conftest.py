"""Helpers for the align tests: simulator scenes turned into the artifacts align consumes.

The layout and layout-cloud inputs are made from the simulator's exact floor
plan (gt/floor_plan.json), so the tests measure align alone.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import shapely
from shapely.geometry import Point, Polygon

from schemas.scene_loader import load_scene
from runtime.stage import Loaded, StageContext
from schemas.depth import DepthOutput, ViewDepth
from schemas.layout import LayoutOutput, ViewLayout
from schemas.sampling import SamplingOutput
from simulate import generate_scene
from stages.cloud_io import write_cloud


@dataclass
class Sim:
    root: Path
    scene: object
    floor_plan: dict

    def train(self):
        return self.scene.manifest.train_views()

    def gt(self, view) -> np.ndarray:
        return np.load(self.root / "gt" / "depth" / f"{view.name}.npy").astype(np.float64)

    def room_of(self, view) -> dict:
        c = view.position
        for room in self.floor_plan["rooms"]:
            if Polygon(room["polygon"]).buffer(1e-6).contains(Point(c[0], c[2])):
                return room
        raise AssertionError(f"{view.name} is in no room")

    def walls(self) -> list[tuple[np.ndarray, np.ndarray]]:
        segs = []
        for room in self.floor_plan["rooms"]:
            poly = np.asarray(room["polygon"], dtype=np.float64)
            segs += [(poly[i], poly[(i + 1) % len(poly)]) for i in range(len(poly))]
        return segs

    def surface_distance(self, pts: np.ndarray) -> np.ndarray:
        """Distance of world points to the nearest floor, ceiling, wall or furniture box surface."""
        pts = np.asarray(pts, dtype=np.float64)
        ceil = min(r["ceiling_y"] for r in self.floor_plan["rooms"])
        best = np.minimum(np.abs(pts[:, 1]), np.abs(pts[:, 1] - ceil))
        xz = pts[:, [0, 2]]
        for a, b in self.walls():
            e = b - a
            t = np.clip(((xz - a) @ e) / (e @ e), 0, 1)
            best = np.minimum(best, np.linalg.norm(xz - (a + t[:, None] * e), axis=1))
        for box in self.floor_plan.get("furniture", []):
            lo, hi = np.asarray(box["min"]), np.asarray(box["max"])
            outside = np.linalg.norm(np.maximum(np.maximum(lo - pts, pts - hi), 0), axis=1)
            inside = np.minimum(pts - lo, hi - pts).min(axis=1)  # > 0 only inside the box
            best = np.minimum(best, np.where(inside > 0, inside, outside))
        return best


def make_sim(tmp: Path, preset="cuboid", views=3, height=64, seed=0, furniture=False) -> Sim:
    fx = "texture,furniture" if furniture else "texture"
    res = generate_scene(
        tmp / f"{preset}-{seed}-{int(furniture)}",
        preset,
        views=views,
        test_views=1,
        height=height,
        seed=seed,
        effects=fx,
        aa_samples=1,
        with_layout=True,
        with_depth=True,
    )
    scene = load_scene(res.out_dir)
    return Sim(res.out_dir, scene, json.loads((res.out_dir / "gt" / "floor_plan.json").read_text()))


def layout_from_gt(sim: Sim, out: Path) -> Loaded:
    """A layout artifact with each train view's exact room in its camera frame."""
    out.mkdir(parents=True, exist_ok=True)
    views = []
    for v in sim.train():
        room = sim.room_of(v)
        pose = v.pose_matrix
        poly = np.asarray(room["polygon"], dtype=np.float64)
        world = np.stack([poly[:, 0], np.zeros(len(poly)), poly[:, 1]], 1)
        cam = (world - pose[:3, 3]) @ pose[:3, :3]  # R^T (p - c), row-wise
        h = float(-pose[1, 3])
        np.save(out / f"{v.name}.npy", np.zeros((2, 8), np.float32))
        views.append(
            ViewLayout(
                view=v.name,
                source="npy",
                boundaries=f"{v.name}.npy",
                floor_polygon=[tuple(p) for p in cam[:, [0, 2]].tolist()],
                camera_height=h,
                ceiling_distance=float(pose[1, 3] - room["ceiling_y"]),
                camera_height_assumed=False,
            )
        )
    return Loaded(data=LayoutOutput(views=views), dir=out)


def sampling_from_gt(sim: Sim, out: Path, spacing=0.05, seed=0) -> Loaded:
    """A layout cloud sampled on the exact walls, floor and ceiling, normals into the room."""
    rng = np.random.default_rng(seed)
    pts, nrm = [], []
    for room in sim.floor_plan["rooms"]:
        poly = np.asarray(room["polygon"], dtype=np.float64)
        fy, cy = room["floor_y"], room["ceiling_y"]
        shape = Polygon(poly)
        area = shape.area
        for y, ny in ((fy, -1.0), (cy, 1.0)):
            n = int(area / spacing**2)
            x0, z0, x1, z1 = shape.bounds
            cand = rng.uniform([x0, z0], [x1, z1], size=(3 * n, 2))
            inside = shapely.contains_xy(shape, cand[:, 0], cand[:, 1])
            c = cand[inside][:n]
            pts.append(np.stack([c[:, 0], np.full(len(c), y), c[:, 1]], 1))
            nrm.append(np.tile([0.0, ny, 0.0], (len(c), 1)))
        for i in range(len(poly)):  # CCW in (x, z): the inward normal of edge e is (-e_z, e_x)
            a, b = poly[i], poly[(i + 1) % len(poly)]
            e = b - a
            length = float(np.linalg.norm(e))
            n = int(length * (fy - cy) / spacing**2)
            s = rng.uniform(0, 1, n)
            y = rng.uniform(cy, fy, n)
            xz = a + s[:, None] * e
            pts.append(np.stack([xz[:, 0], y, xz[:, 1]], 1))
            inward = np.array([-e[1], e[0]]) / length
            nrm.append(np.tile([inward[0], 0.0, inward[1]], (n, 1)))
    p = np.concatenate(pts)
    n = np.concatenate(nrm)
    files = write_cloud(out, p, np.full_like(p, 0.5), n, p, np.ones(len(p), bool))
    return Loaded(
        data=SamplingOutput(cloud=files, density_per_m2=1 / spacing**2, points_per_surface={"wall": 0}),
        dir=out,
    )


def depth_loaded(out: Path, maps: dict[str, np.ndarray], kind="metric") -> Loaded:
    out.mkdir(parents=True, exist_ok=True)
    views = []
    for name, m in maps.items():
        np.save(out / f"{name}.npy", m.astype(np.float32))
        views.append(
            ViewDepth(
                view=name,
                depth=f"{name}.npy",
                kind=kind,
                source="file",
                valid_fraction=float(np.isfinite(m).mean()),
            )
        )
    return Loaded(data=DepthOutput(views=views), dir=out)


def run_align(sim: Sim, tmp: Path, depth: Loaded, layout=None, sampling=None, **params):
    from stages import align

    out = tmp / "align-out"
    out.mkdir(parents=True, exist_ok=True)
    ctx = StageContext(
        scene=sim.scene,
        params=align.Params(**params),
        inputs={"depth": depth, "layout": layout, "sampling": sampling},
        out_dir=out,
    )
    return align.run(ctx), out


@pytest.fixture(scope="module")
def sim_tmp(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("sim")


@pytest.fixture(scope="session")
def kit():
    """The helpers above, as a fixture (conftest modules are not importable by name)."""
    from types import SimpleNamespace

    return SimpleNamespace(
        make_sim=make_sim,
        layout_from_gt=layout_from_gt,
        sampling_from_gt=sampling_from_gt,
        depth_loaded=depth_loaded,
        run_align=run_align,
    )
