"""A simulated scene whose supplied layout is wrong by one wall: docs/training.md's `cubw` (issue 39).

Copies a one-room simulated scene (`pano-pipe simulate ... --with-layout`) to OUT and rewrites each
training view's supplied layout (HorizonNet JSON) for the room's floor polygon clipped to
x <= X_MAX: the +x wall moves into the room, a layout wall across open space, as zind_pair's
joint-visible polygon has beside its kitchen island. Images, poses and ground truth are unchanged.

    PYTHONPATH=$PWD .venv/bin/python scripts/shift_layout_wall.py /tmp/one/cub /tmp/one/cubw --x-max 1.3165
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import numpy as np

#: HorizonNet's ceiling at 50 units above the camera (simulate/layout.py writes the same)
Z0 = 50.0


def horizonnet_uv(polygon_xz: np.ndarray, pose: np.ndarray, camera_height: float, ceiling_height: float) -> list:
    """Corners of the floor polygon (world x, z) seen from a camera (pose: camera-to-world) as
    HorizonNet's uv pairs (ceiling, floor), sorted by u."""
    rotation, centre = pose[:3, :3], pose[:3, 3]
    world = np.stack([polygon_xz[:, 0], np.full(len(polygon_xz), centre[1]), polygon_xz[:, 1]], axis=1)
    cam = (world - centre) @ rotation
    lon = np.arctan2(cam[:, 0], cam[:, 2])
    dist = np.hypot(cam[:, 0], cam[:, 2])
    u = lon / (2 * np.pi) + 0.5
    v_ceiling = 0.5 - np.arctan((ceiling_height - camera_height) / dist) / np.pi
    v_floor = 0.5 + np.arctan(camera_height / dist) / np.pi
    return [[float(u[i]), float(v)] for i in np.argsort(u, kind="stable") for v in (v_ceiling[i], v_floor[i])]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--x-max", type=float, required=True, help="the +x wall's new x (m)")
    a = ap.parse_args()
    plan = json.loads((a.scene / "gt" / "floor_plan.json").read_text())
    if len(plan["rooms"]) != 1:
        raise SystemExit(f"{a.scene}: one room expected, found {len(plan['rooms'])}")
    room = plan["rooms"][0]
    polygon = np.asarray(room["polygon"], dtype=np.float64)
    polygon[:, 0] = np.minimum(polygon[:, 0], a.x_max)
    ceiling_height = float(room["floor_y"]) - float(room["ceiling_y"])
    shutil.rmtree(a.out, ignore_errors=True)
    shutil.copytree(a.scene, a.out)
    scene = json.loads((a.out / "scene.json").read_text())
    scene["name"] = a.out.name
    (a.out / "scene.json").write_text(json.dumps(scene, indent=1))
    for view in scene["views"]:
        if view.get("split") != "train" or not view.get("layout"):
            continue
        h = float(view["camera_height"])
        uv = horizonnet_uv(polygon, np.asarray(view["pose"], dtype=np.float64), h, ceiling_height)
        doc = {"z0": Z0, "z1": -Z0 * h / (ceiling_height - h), "uv": uv}
        (a.out / view["layout"]).write_text(json.dumps(doc))
        print(f"{view['name']}: layout for x <= {a.x_max:g}")


if __name__ == "__main__":
    main()
