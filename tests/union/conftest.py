"""Fixtures for the union tests: simulator scenes and layouts built from their ground truth."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from shapely.geometry import Point, Polygon

from schemas.layout import LayoutOutput, ViewLayout


def _gt_layouts(scene_dir: Path, noise: float = 0.0, shrink: float = 0.0, seed: int = 0) -> LayoutOutput:
    """Per train view: the true floor polygon of the camera's room (the doorway closed, as
    HorizonNet's JSON describes it), in the camera frame; optional vertex noise (m, std) and
    inward shrink (m) to mimic an imperfect layout estimate."""
    rng = np.random.default_rng(seed)
    gt = json.loads((scene_dir / "gt" / "floor_plan.json").read_text())
    manifest = json.loads((scene_dir / "scene.json").read_text())
    views = []
    for v in manifest["views"]:
        if v["split"] != "train":
            continue
        pose = np.asarray(v["pose"])
        pos = pose[:3, 3]
        room = next(
            r for r in gt["rooms"] if Polygon(r["polygon"]).buffer(1e-9).contains(Point(pos[0], pos[2]))
        )
        poly = Polygon(room["polygon"])
        if shrink:
            poly = poly.buffer(-shrink, join_style="mitre")
        w = np.asarray(poly.exterior.coords)[:-1]
        w = w + rng.normal(0.0, noise, w.shape) if noise else w
        world = np.stack([w[:, 0], np.full(len(w), room["floor_y"]), w[:, 1]], axis=1)
        cam = (world - pos) @ pose[:3, :3]  # R^T (p - t)
        h = room["floor_y"] - pos[1]
        d = pos[1] - room["ceiling_y"]
        views.append(
            ViewLayout(
                view=v["name"],
                source="npy",
                boundaries=f"{v['name']}.npy",
                floor_polygon=[(float(x), float(z)) for x, z in cam[:, [0, 2]]],
                camera_height=float(h),
                ceiling_distance=float(d),
                camera_height_assumed=False,
            )
        )
    return LayoutOutput(views=views)


@pytest.fixture(scope="session")
def two_rooms_scene(tmp_path_factory) -> Path:
    from simulate import generate_scene

    out = tmp_path_factory.mktemp("union") / "two_rooms"
    generate_scene(
        out, preset="two-rooms", views=4, test_views=1, height=32, seed=3, effects="none", aa_samples=1
    )
    return out


@pytest.fixture(scope="session")
def l_shape_scene(tmp_path_factory) -> Path:
    from simulate import generate_scene

    out = tmp_path_factory.mktemp("union") / "l_shape"
    generate_scene(
        out, preset="l-shape", views=3, test_views=1, height=32, seed=1, effects="none", aa_samples=1
    )
    return out


@pytest.fixture(scope="session")
def gt_layouts():
    """gt_layouts(scene_dir, noise=0, shrink=0, seed=0) -> LayoutOutput from the simulator's ground truth."""
    return _gt_layouts
