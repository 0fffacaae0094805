"""Fly-through videos: a camera path through the views' poses, rendered and written as mp4.

Between consecutive key poses, positions move linearly and rotations by
spherical linear interpolation (scipy's Slerp). Frames are spread over the
segments in proportion to their length (metres plus half a metre per radian
turned), so the camera moves at a steady pace whatever the spacing of the
views. A path of one view spins the camera once about the vertical axis.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial.transform import Rotation, Slerp

#: Metres of path per radian of turn when spacing frames (a pure rotation still takes time).
TURN_WEIGHT_M = 0.5


def interpolate_poses(poses: list[np.ndarray] | np.ndarray, frames: int) -> np.ndarray:
    """[frames,4,4] camera-to-world poses through the key poses, first and last included."""
    keys = np.asarray(poses, dtype=np.float64)
    if keys.ndim != 3 or keys.shape[1:] != (4, 4) or len(keys) == 0:
        raise ValueError(f"expected key poses [K,4,4], got shape {keys.shape}")
    if frames < 1:
        raise ValueError("frames must be >= 1")
    if len(keys) == 1:
        return spin_poses(keys[0], frames)
    rots = Rotation.from_matrix(keys[:, :3, :3])
    pos = keys[:, :3, 3]
    seg = np.linalg.norm(np.diff(pos, axis=0), axis=1)
    turn = (rots[:-1].inv() * rots[1:]).magnitude()
    length = seg + TURN_WEIGHT_M * turn
    cum = np.concatenate([[0.0], np.cumsum(length)])
    if cum[-1] <= 1e-12:  # all key poses equal: a still shot
        return np.repeat(keys[:1], frames, axis=0)
    # Parametrise the keys by normalised arc length; equal-length steps in that parameter.
    knots = cum / cum[-1]
    # Collapse zero-length segments (repeated poses) so knots strictly increase.
    keep = np.concatenate([[True], np.diff(knots) > 1e-12])
    knots, rots, pos = knots[keep], rots[keep], pos[keep]
    s = np.linspace(0.0, 1.0, frames) if frames > 1 else np.zeros(1)
    out = np.tile(np.eye(4), (frames, 1, 1))
    out[:, :3, :3] = Slerp(knots, rots)(s).as_matrix()
    for i in range(3):
        out[:, i, 3] = np.interp(s, knots, pos[:, i])
    return out


def spin_poses(pose: np.ndarray, frames: int) -> np.ndarray:
    """One full turn about the world vertical (y) axis through the pose's position."""
    out = np.tile(np.asarray(pose, dtype=np.float64), (frames, 1, 1))
    for k, a in enumerate(np.linspace(0.0, 2 * np.pi, frames, endpoint=False)):
        ry = Rotation.from_euler("y", a).as_matrix()
        out[k, :3, :3] = ry @ pose[:3, :3]
    return out


def path_views(scene, path: str):
    """The views a path goes through: 'train', 'test', 'all' (manifest order) or 'name1,name2,...'."""
    from pipeline.errors import PanoError

    m = scene.manifest
    if path == "train":
        views = m.train_views()
    elif path == "test":
        views = m.test_views()
    elif path == "all":
        views = list(m.views)
    else:
        views = []
        for name in (n.strip() for n in path.split(",") if n.strip()):
            try:
                views.append(m.view(name))
            except KeyError:
                raise PanoError(
                    scene.root / "scene.json",
                    f"--path names view {name!r}, which the scene lacks "
                    f"(views: {', '.join(v.name for v in m.views)}; or use train / test / all)",
                ) from None
    if not views:
        raise PanoError(scene.root / "scene.json", f"path {path!r} has no views")
    return views


@dataclass
class FlythroughResult:
    path: Path
    frames: int
    size: tuple[int, int]  # (H, W)
    seconds: float


def write_video(frames_rgb, out_path: Path, fps: float = 24.0) -> int:
    """Write float RGB [H,W,3] frames (an iterable) as mp4 ('mp4v'); returns the frame count."""
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    writer = None
    n = 0
    tmp = out_path.with_name(f".tmp-{out_path.name}")
    try:
        for rgb in frames_rgb:
            arr = (np.clip(rgb, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
            if writer is None:
                h, w = arr.shape[:2]
                writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), float(fps), (w, h))
                if not writer.isOpened():
                    raise OSError(f"{out_path}: OpenCV cannot open an mp4v video writer")
            writer.write(cv2.cvtColor(arr, cv2.COLOR_RGB2BGR))
            n += 1
    finally:
        if writer is not None:
            writer.release()
    tmp.replace(out_path)  # a finished file only: an interrupted render leaves no half video
    return n


def render_flythrough(g, poses: np.ndarray, camera, out_path: Path, fps: float = 24.0, backend=None,
                      track=None) -> FlythroughResult:
    from evaluation.model_io import render_pose

    t0 = time.perf_counter()
    seq = track(poses, "render: frames", total=len(poses)) if track else poses

    def frames():
        for pose in seq:
            yield render_pose(g, pose, camera, backend=backend).image

    n = write_video(frames(), out_path, fps)
    return FlythroughResult(Path(out_path), n, (int(camera.height), int(camera.width)), time.perf_counter() - t0)
