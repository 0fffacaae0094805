"""Fixtures for the sampling tests: simulator scenes, their true floor plans as union rooms,
and a hand-built L-shaped scene whose panoramas encode their own pixel coordinates."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from schemas.union import Room, UnionOutput


def _gt_union(scene_dir: Path) -> UnionOutput:
    """The simulator's true floor plan as the union stage's output (one room: the outline)."""
    gt = json.loads((scene_dir / "gt" / "floor_plan.json").read_text())
    outline = [tuple(p) for p in gt["outline"]]
    r0 = gt["rooms"][0]
    train = sorted(n for n, c in gt["cameras"].items() if c["split"] == "train")
    room = Room(polygon=outline, floor_y=r0["floor_y"], ceiling_y=r0["ceiling_y"], views=train)
    return UnionOutput(rooms=[room], floor_plan="floor_plan.json", drawing="floor_plan.png", area_m2=0.0)


@pytest.fixture(scope="session")
def gt_union():
    return _gt_union


@pytest.fixture(scope="session")
def two_rooms(tmp_path_factory) -> Path:
    from simulate import generate_scene

    out = tmp_path_factory.mktemp("sampling") / "two_rooms"
    generate_scene(
        out, preset="two-rooms", views=3, test_views=1, height=64, seed=5, effects="none", aa_samples=1
    )
    return out


def yaw_pose(yaw: float, position) -> list[list[float]]:
    c, s = np.cos(yaw), np.sin(yaw)
    m = np.eye(4)
    m[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    m[:3, 3] = position
    return m.tolist()


# L-shaped room: arm A along x (z in [0, 2]), arm B along z (x in [0, 2]); reflex corner at (2, 2).
L_POLYGON = [(0.0, 0.0), (6.0, 0.0), (6.0, 2.0), (2.0, 2.0), (2.0, 6.0), (0.0, 6.0)]
L_FLOOR_Y, L_CEILING_Y = 0.0, -2.5
# Camera "a" sits in arm A right beside the reflex corner; camera "b" far up arm B.
L_CAMERAS = {"a": ((2.5, -1.5, 1.6), 0.4), "b": ((1.0, -1.4, 5.5), -2.0), "t": ((1.0, -1.5, 1.0), 0.0)}


@pytest.fixture(scope="session")
def coded_l_scene(tmp_path_factory) -> Path:
    """Views whose images hold R = column, G = row (as 8-bit integers, W = 256, H = 128), B = 100 * view index,
    so a bilinear lookup returns the projected pixel coordinates exactly."""
    root = tmp_path_factory.mktemp("sampling") / "coded_l"
    (root / "images").mkdir(parents=True)
    h, w = 128, 256
    cols, rows = np.meshgrid(np.arange(w), np.arange(h))
    views = []
    for i, (name, (pos, yaw)) in enumerate(L_CAMERAS.items()):
        rgb = np.stack([cols, rows, np.full_like(cols, 100 * i)], axis=-1).astype(np.uint8)
        cv2.imwrite(str(root / "images" / f"{name}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        views.append(
            {
                "name": name,
                "image": f"images/{name}.png",
                "pose": yaw_pose(yaw, pos),
                "split": "test" if name == "t" else "train",
                "camera_height": -pos[1],
            }
        )
    (root / "scene.json").write_text(json.dumps({"name": "coded_l", "views": views}))
    return root


@pytest.fixture
def coded_l_union() -> UnionOutput:
    room = Room(polygon=L_POLYGON, floor_y=L_FLOOR_Y, ceiling_y=L_CEILING_Y, views=["a", "b"])
    return UnionOutput(rooms=[room], floor_plan="floor_plan.json", drawing="floor_plan.png", area_m2=20.0)


def _gt_view_layouts(scene_dir: Path):
    """Per train view the true floor polygon of the camera's room (doorway closed), in its camera frame."""
    from shapely.geometry import Point, Polygon

    from schemas.layout import LayoutOutput, ViewLayout

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
        w = np.asarray(room["polygon"])
        world = np.stack([w[:, 0], np.full(len(w), room["floor_y"]), w[:, 1]], axis=1)
        cam = (world - pos) @ pose[:3, :3]
        views.append(
            ViewLayout(
                view=v["name"],
                source="npy",
                boundaries="b.npy",
                floor_polygon=[(float(x), float(z)) for x, z in cam[:, [0, 2]]],
                camera_height=float(room["floor_y"] - pos[1]),
                ceiling_distance=float(pos[1] - room["ceiling_y"]),
                camera_height_assumed=False,
            )
        )
    return LayoutOutput(views=views)


@pytest.fixture(scope="session")
def gt_view_layouts():
    return _gt_view_layouts
