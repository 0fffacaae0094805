"""Held-out scenes from ../shared/data/zind_pair, for docs/training.md's real-pixel checks.

Writes OUT/zind_a (pano_18 trains, pano_12 held out) and OUT/zind_b (the other way round), each
the pair's images and scene.json with one view's split set to "test" and the nadir cap set. With
--with-layout the training view also gets a supplied layout: the dataset's `joint_visible_layout`
(the floor polygon both panoramas see, with its `ceiling_height`) ray-cast from the training
camera into [2,W] boundary latitudes, plus layout_overlay/<view>.png (the report's layout picture:
the boundaries on the image and the floor plan) to check by eye that they land on the wall edges.
The polygon is only the jointly visible floor, so a few of its edges cross open space (beside the
kitchen island): a rough layout.

    PYTHONPATH=$PWD .venv/bin/python scripts/zind_pair_scenes.py /tmp/zind --with-layout
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import cv2
import numpy as np

from evaluation.report_sections import plot_layout_view
from layoutnet.postprocess import polygon_to_boundaries

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "zind_pair"
HELD_OUT = {"zind_a": "pano_12", "zind_b": "pano_18"}
BOUNDARY_WIDTH = 1024


def dataset_to_world(xy: np.ndarray) -> np.ndarray:
    """Floor points of the dataset's frame (z up, image centre along +y) as world (X, Z): the
    scene.json's conversion X = x, Z = -y (a mirror; it puts pano_12's annotated position at its
    pose)."""
    return np.stack([xy[:, 0], -xy[:, 1]], axis=1)


def training_view_room(view: dict, polygon_xz: np.ndarray, ceiling_height: float) -> tuple[np.ndarray, np.ndarray]:
    """The room seen from the view's camera (pose = camera-to-world): [2,W] boundary latitudes and
    the floor polygon in the camera frame (x, z)."""
    pose = np.asarray(view["pose"], dtype=np.float64)
    rotation, centre = pose[:3, :3], pose[:3, 3]
    world = np.stack([polygon_xz[:, 0], np.full(len(polygon_xz), centre[1]), polygon_xz[:, 1]], axis=1)
    camera = (world - centre) @ rotation  # world -> camera: Rᵀ (p - c), row-wise
    height = float(view["camera_height"])
    bounds = polygon_to_boundaries(camera[:, [0, 2]], height, ceiling_height - height, BOUNDARY_WIDTH)
    if not np.all(np.isfinite(bounds)):
        raise SystemExit(f"{view['name']}: the camera is outside joint_visible_layout")
    return bounds, camera[:, [0, 2]]


def make_scene(out: Path, name: str, nadir_mask_deg: float, with_layout: bool) -> None:
    scene = json.loads((DATA / "scene.json").read_text())
    annotation = json.loads((DATA / "relative_pose_annotation.json").read_text())
    folder = out / name
    shutil.copytree(DATA / "images", folder / "images", dirs_exist_ok=True)
    scene["name"], scene["nadir_mask_deg"] = name, nadir_mask_deg
    polygon = dataset_to_world(np.asarray(annotation["joint_visible_layout"], dtype=np.float64))
    for view in scene["views"]:
        view["split"] = "test" if view["name"] == HELD_OUT[name] else "train"
        if with_layout and view["split"] == "train":
            ceiling_height = float(annotation["ceiling_height"])
            bounds, room = training_view_room(view, polygon, ceiling_height)
            (folder / "layout").mkdir(exist_ok=True)
            np.save(folder / "layout" / f"{view['name']}.npy", bounds)
            view["layout"] = f"layout/{view['name']}.npy"
            (folder / "layout_overlay").mkdir(exist_ok=True)
            image = cv2.cvtColor(cv2.imread(str(folder / view["image"])), cv2.COLOR_BGR2RGB) / 255.0
            height = float(view["camera_height"])
            plot_layout_view(image, bounds, room, height, ceiling_height - height,
                             f"{view['name']}: joint_visible_layout", folder / "layout_overlay" / f"{view['name']}.png")
    (folder / "scene.json").write_text(json.dumps(scene, indent=1))
    print(f"wrote {folder} ({HELD_OUT[name]} held out{', layout supplied' if with_layout else ''})")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--nadir-mask-deg", type=float, default=35.0)
    ap.add_argument("--with-layout", action="store_true")
    args = ap.parse_args()
    if not DATA.is_dir():
        raise SystemExit(f"{DATA}: zind_pair is not there (see ../shared/data/README.md)")
    for name in HELD_OUT:
        make_scene(args.out, name, args.nadir_mask_deg, args.with_layout)


if __name__ == "__main__":
    main()
