"""Bring other capture conventions into a pano-pipe scene folder.

nerfstudio `transforms.json` (camera_model EQUIRECTANGULAR): `transform_matrix`
is camera-to-world with OpenGL camera axes (x right, y up, z back) and its
image centre looks along -z, so flipping the camera's y and z axes gives our
OpenCV camera with the same pixel-to-direction mapping. nerfstudio worlds are
usually z-up; ours is y-down, so the world is rotated by `WORLD_TO_YDOWN`.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

from pipeline.errors import PanoError
from schemas.scene import SceneManifest, View

GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])

#: Rotations taking a world with the given up axis to our y-down world.
WORLD_TO_YDOWN = {
    "+z": np.array([[1, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]], dtype=np.float64),
    "+y": np.diag([1.0, -1.0, -1.0, 1.0]),
    "-y": np.eye(4),
}


def nerfstudio_to_pose(transform_matrix, world_up: str = "+z") -> np.ndarray:
    """A nerfstudio camera-to-world matrix as our camera-to-world (OpenCV camera, y-down world)."""
    m = np.asarray(transform_matrix, dtype=np.float64)
    if m.shape == (3, 4):
        m = np.vstack([m, [0, 0, 0, 1]])
    return WORLD_TO_YDOWN[world_up] @ m @ GL_TO_CV


def pose_to_nerfstudio(pose, world_up: str = "+z") -> np.ndarray:
    """The inverse of `nerfstudio_to_pose` (for exporting and for tests)."""
    return np.linalg.inv(WORLD_TO_YDOWN[world_up]) @ np.asarray(pose, dtype=np.float64) @ GL_TO_CV


def import_nerfstudio(
    transforms: Path, out: Path, world_up: str = "+z", test_every: int = 8, name: str | None = None
) -> Path:
    """Write a scene folder at `out` from a nerfstudio `transforms.json`; returns its scene.json."""
    if world_up not in WORLD_TO_YDOWN:
        raise PanoError("--world-up", f"must be one of {sorted(WORLD_TO_YDOWN)}, got {world_up!r}")
    try:
        meta = json.loads(Path(transforms).read_text())
    except FileNotFoundError:
        raise PanoError(transforms, "file does not exist") from None
    except json.JSONDecodeError as e:
        raise PanoError(transforms, f"invalid JSON at line {e.lineno}: {e.msg}") from None
    frames = meta.get("frames")
    if not isinstance(frames, list) or not frames:
        raise PanoError(transforms, "no 'frames' list")
    model = meta.get("camera_model", "EQUIRECTANGULAR")
    base = Path(transforms).parent
    test_names = {Path(p).name for p in meta.get("test_filenames", [])}
    (out / "images").mkdir(parents=True, exist_ok=True)
    views = []
    for i, frame in enumerate(frames):
        if frame.get("camera_model", model) != "EQUIRECTANGULAR":
            raise PanoError(transforms, f"frames.{i}: camera_model must be EQUIRECTANGULAR")
        src = base / frame["file_path"]
        if not src.is_file():
            raise PanoError(src, f"image missing (named by frames.{i}.file_path)")
        view_name = src.stem
        dst = out / "images" / f"{view_name}{src.suffix}"
        shutil.copy2(src, dst)
        if test_names:
            split = "test" if src.name in test_names else "train"
        else:
            split = "test" if test_every > 0 and i % test_every == test_every - 1 else "train"
        pose = nerfstudio_to_pose(frame["transform_matrix"], world_up)
        views.append(View(name=view_name, image=f"images/{dst.name}", pose=pose.tolist(), split=split))
    manifest = SceneManifest(name=name or out.name, views=views)
    path = out / "scene.json"
    path.write_text(manifest.model_dump_json(indent=2, exclude_none=True))
    return path
