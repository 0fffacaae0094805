"""Fly-through videos: a camera path through the views, rendered and written as H.264 mp4.

Walk paths (`walk_poses`, used for `--path train|test|all|names`): the camera
positions follow a centripetal Catmull-Rom curve through the views' positions
(no cusps, no loops, little overshoot between close views), sampled at equal
steps of arc length so the pace is steady however the views are spaced. The
camera is level (its y axis is the world's +y, gravity) and looks along the
curve's horizontal tangent: yaw = atan2(t_x, t_z), lightly smoothed (a Gaussian
over `YAW_SMOOTH_M` metres of path) so corners turn rather than snap. Where the
camera barely moves sideways (a standstill, a purely vertical step) it keeps
the last direction it looked. A path with no horizontal movement at all (one
view, or views at one spot) spins once about the vertical axis instead.
The same poses serve both modes: a perspective frame looks ahead, and a
panoramic frame's centre column looks ahead.

Camera path files (`read_camera_path`, `--path FILE.json`): nerfstudio's
camera_path.json, converted to pano-pipe poses with the same rule as
`pano-pipe import-nerfstudio` (`pipeline.importers.nerfstudio_to_pose`: OpenGL
camera axes to OpenCV ones, the nerfstudio world rotated by `--world-up` into
our y-down world), one rendered frame per entry, orientations as given.

Videos (`write_video`): H.264 (libx264), yuv420p, `+faststart`, through the
ffmpeg binary that imageio-ffmpeg bundles; browsers play it. Frames are
written to a hidden temporary file that is renamed into place when complete.
"""

from __future__ import annotations

import math
import os
import re
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.spatial.transform import Rotation, Slerp

#: Metres of path per radian of turn when spacing frames (a pure rotation still takes time).
TURN_WEIGHT_M = 0.5
#: Gaussian smoothing of the walk yaw, in metres of path (sigma).
YAW_SMOOTH_M = 0.15
#: Horizontal movement (metres per frame step, as a share of the mean step) below which the camera keeps its direction.
STANDSTILL_SHARE = 1e-3
#: x264 constant rate factor (lower = better; 18 is visually near lossless).
CRF = 18


def interpolate_poses(poses: list[np.ndarray] | np.ndarray, frames: int) -> np.ndarray:
    """[frames,4,4] camera-to-world poses through the key poses, orientations slerped
    between the keys' own (first and last included). Kept for callers that want the
    views' own orientations; the render command uses `walk_poses`."""
    keys = _keys(poses, frames)
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
    knots = cum / cum[-1]
    keep = np.concatenate([[True], np.diff(knots) > 1e-12])
    knots, rots, pos = knots[keep], rots[keep], pos[keep]
    s = np.linspace(0.0, 1.0, frames) if frames > 1 else np.zeros(1)
    out = np.tile(np.eye(4), (frames, 1, 1))
    out[:, :3, :3] = Slerp(knots, rots)(s).as_matrix()
    for i in range(3):
        out[:, i, 3] = np.interp(s, knots, pos[:, i])
    return out


def _keys(poses, frames: int) -> np.ndarray:
    keys = np.asarray(poses, dtype=np.float64)
    if keys.ndim != 3 or keys.shape[1:] != (4, 4) or len(keys) == 0:
        raise ValueError(f"expected key poses [K,4,4], got shape {keys.shape}")
    if frames < 1:
        raise ValueError("frames must be >= 1")
    return keys


def level_rotation(yaw: float) -> np.ndarray:
    """Camera-to-world rotation of a level camera (y axis = world +y, down) whose forward
    axis z is (sin yaw, 0, cos yaw): yaw is the longitude it looks at."""
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _yaw_of(rot: np.ndarray) -> float:
    """The longitude a camera-to-world rotation's forward axis looks at (its horizontal part)."""
    z = rot[:, 2]
    return math.atan2(z[0], z[2]) if math.hypot(z[0], z[2]) > 1e-9 else 0.0


def catmull_rom(points: np.ndarray, u: np.ndarray, alpha: float = 0.5) -> np.ndarray:
    """Centripetal (alpha = 0.5) Catmull-Rom curve through `points` [K,3] (consecutive points
    distinct), evaluated at u in [0, K-1] (segment i spans u in [i, i+1]); [len(u),3].
    The ends are extended by mirrored phantom points, so two points give a straight line."""
    p = np.asarray(points, dtype=np.float64)
    ext = np.vstack([2 * p[0] - p[1], p, 2 * p[-1] - p[-2]])
    u = np.clip(np.asarray(u, dtype=np.float64), 0.0, len(p) - 1)
    seg = np.minimum(np.floor(u).astype(int), len(p) - 2)
    f = (u - seg)[:, None]
    p0, p1, p2, p3 = ext[seg], ext[seg + 1], ext[seg + 2], ext[seg + 3]

    def knot(a, b):
        return np.maximum(np.linalg.norm(b - a, axis=1, keepdims=True), 1e-12) ** alpha

    t0 = np.zeros_like(f)
    t1 = t0 + knot(p0, p1)
    t2 = t1 + knot(p1, p2)
    t3 = t2 + knot(p2, p3)
    t = t1 + f * (t2 - t1)
    a1 = (t1 - t) / (t1 - t0) * p0 + (t - t0) / (t1 - t0) * p1
    a2 = (t2 - t) / (t2 - t1) * p1 + (t - t1) / (t2 - t1) * p2
    a3 = (t3 - t) / (t3 - t2) * p2 + (t - t2) / (t3 - t2) * p3
    b1 = (t2 - t) / (t2 - t0) * a1 + (t - t0) / (t2 - t0) * a2
    b2 = (t3 - t) / (t3 - t1) * a2 + (t - t1) / (t3 - t1) * a3
    return (t2 - t) / (t2 - t1) * b1 + (t - t1) / (t2 - t1) * b2


def walk_poses(poses: list[np.ndarray] | np.ndarray, frames: int, smooth_m: float = YAW_SMOOTH_M) -> np.ndarray:
    """[frames,4,4] level camera-to-world poses walking through the key poses' positions
    (first and last included), each looking along the direction of motion (module doc)."""
    keys = _keys(poses, frames)
    pos = keys[:, :3, 3]
    keep = np.concatenate([[True], np.linalg.norm(np.diff(pos, axis=0), axis=1) > 1e-9])
    pts = pos[keep]
    start_yaw = _yaw_of(keys[0, :3, :3])
    if len(pts) == 1 or np.ptp(pts[:, [0, 2]], axis=0).max() <= 1e-9:
        out = spin_poses(keys[0], frames)  # nowhere to walk: look around instead
        for k in range(frames):
            out[k, :3, :3] = level_rotation(start_yaw + 2 * math.pi * k / frames)
        out[:, :3, 3] = np.linspace(pts[0], pts[-1], frames)
        return out
    # dense samples of the curve -> arc length -> equal steps of arc length
    dense_u = np.linspace(0.0, len(pts) - 1, 256 * (len(pts) - 1) + 1)
    dense = catmull_rom(pts, dense_u)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(dense, axis=0), axis=1))])
    s = np.linspace(0.0, arc[-1], frames) if frames > 1 else np.zeros(1)
    u = np.interp(s, arc, dense_u)
    xyz = catmull_rom(pts, u)
    # tangent: the curve's derivative by a small central difference in u
    du = 1e-4
    tan = catmull_rom(pts, np.minimum(u + du, len(pts) - 1)) - catmull_rom(pts, np.maximum(u - du, 0.0))
    horiz = np.hypot(tan[:, 0], tan[:, 2])
    moving = horiz > 1e-9 * max(1.0, arc[-1])
    raw = np.arctan2(tan[:, 0], tan[:, 2])
    yaw = np.empty(frames)
    last = raw[np.argmax(moving)] if moving.any() else start_yaw  # before the first move: the first direction
    for k in range(frames):
        if moving[k]:
            last = raw[k] if k == 0 else yaw[k - 1] + _wrap(raw[k] - yaw[k - 1])  # unwrapped
        yaw[k] = last
    step = arc[-1] / max(frames - 1, 1)
    if smooth_m > 0 and frames > 2 and step > 0:
        yaw = gaussian_filter1d(yaw, sigma=smooth_m / step, mode="nearest")
    out = np.tile(np.eye(4), (frames, 1, 1))
    for k in range(frames):
        out[k, :3, :3] = level_rotation(float(yaw[k]))
    out[:, :3, 3] = xyz
    return out


def _wrap(a):
    return (a + math.pi) % (2 * math.pi) - math.pi


def spin_poses(pose: np.ndarray, frames: int) -> np.ndarray:
    """One full turn about the world vertical (y) axis through the pose's position."""
    out = np.tile(np.asarray(pose, dtype=np.float64), (frames, 1, 1))
    for k, a in enumerate(np.linspace(0.0, 2 * np.pi, frames, endpoint=False)):
        ry = Rotation.from_euler("y", a).as_matrix()
        out[k, :3, :3] = ry @ pose[:3, :3]
    return out


def path_views(scene, path: str):
    """The views a path goes through: 'train', 'test', 'all' (manifest order) or 'name1,name2,...'."""
    from runfs.errors import PanoError

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


def is_path_file(path: str) -> bool:
    """`--path` names a camera path file (rather than train/test/all/view names)."""
    return path.lower().endswith(".json") or (os.sep in path or "/" in path) or Path(path).is_file()


# ---------------------------------------------------------------------------------------------
# nerfstudio camera_path.json

@dataclass
class CameraPath:
    poses: np.ndarray  # [N,4,4] pano-pipe camera-to-world (OpenCV camera, y-down world)
    kind: str  # "perspective" | "equirectangular"
    fov_deg: float  # vertical field of view (perspective), from the first entry
    height: int | None
    width: int | None
    fps: float | None
    aspect: float | None = None  # width / height of the first entry, where given


_CAMERA_TYPES = {"perspective": "perspective", "equirectangular": "equirectangular"}


def _number(value, where: Path, field: str, positive: bool = True) -> float:
    from runfs.errors import PanoError

    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(float(value)):
        raise PanoError(where, f"{field}: must be a finite number, got {str(value)[:40]!r}")
    if positive and not float(value) > 0:
        raise PanoError(where, f"{field}: must be positive, got {value!r}")
    return float(value)


def read_camera_path(file: str | Path, world_up: str = "+z") -> CameraPath:
    """A nerfstudio camera_path.json as pano-pipe poses; every problem a one-line PanoError
    naming the file and the field."""
    from runfs.errors import PanoError, read_json
    from pipeline.importers import check_world_up, nerfstudio_to_pose, rigid_matrix

    file = Path(file)
    check_world_up(world_up)
    if not file.is_file():
        raise PanoError(file, "no such camera path file (--path takes train, test, all, view names or a "
                              "nerfstudio camera_path.json)")
    data = read_json(file)
    if not isinstance(data, dict):
        raise PanoError(file, f"must be a JSON object with a camera_path list, got {type(data).__name__}")
    entries = data.get("camera_path")
    if not isinstance(entries, list) or not entries:
        raise PanoError(file, "camera_path: must be a non-empty list of {camera_to_world, fov, aspect}")
    ctype = data.get("camera_type", "perspective")
    if not isinstance(ctype, str) or ctype.lower() not in _CAMERA_TYPES:
        raise PanoError(file, f"camera_type: must be perspective or equirectangular, got {str(ctype)[:40]!r}")
    poses, fov, aspect = [], None, None
    for i, e in enumerate(entries):
        field = f"camera_path.{i}"
        if not isinstance(e, dict):
            raise PanoError(file, f"{field}: must be an object, got {type(e).__name__}")
        c2w = e.get("camera_to_world")
        if not isinstance(c2w, list) or len(c2w) != 16:
            got = f"{len(c2w)} entries" if isinstance(c2w, list) else type(c2w).__name__
            raise PanoError(file, f"{field}.camera_to_world: must be 16 numbers (a row-major 4x4), got {got}")
        m = rigid_matrix([c2w[0:4], c2w[4:8], c2w[8:12], c2w[12:16]], file, f"{field}.camera_to_world")
        poses.append(nerfstudio_to_pose(m, world_up))
        if "fov" in e:
            f = _number(e["fov"], file, f"{field}.fov")
            if not f < 180:
                raise PanoError(file, f"{field}.fov: must be below 180 degrees, got {f:g}")
            fov = f if fov is None else fov
        if "aspect" in e:
            a = _number(e["aspect"], file, f"{field}.aspect")
            aspect = a if aspect is None else aspect
    size = []
    for key in ("render_height", "render_width"):
        v = data.get(key)
        if v is not None:
            if isinstance(v, bool) or not isinstance(v, (int, float)) or v != int(v) or not 8 <= v <= 16384:
                raise PanoError(file, f"{key}: must be a whole number of pixels in 8..16384, got {str(v)[:40]!r}")
            v = int(v)
        size.append(v)
    fps = data.get("fps")
    fps = _number(fps, file, "fps") if fps is not None else None
    if data.get("seconds") is not None:
        _number(data["seconds"], file, "seconds")
    return CameraPath(np.stack(poses), _CAMERA_TYPES[ctype.lower()], fov if fov is not None else 50.0,
                      size[0], size[1], fps, aspect)


# ---------------------------------------------------------------------------------------------
# output names and video writing

def output_path(render_dir: Path, path: str, mode: str, overwrite: bool = False) -> Path:
    """`render_dir/flythrough-<path>-<mode>.mp4`; when that exists and not `overwrite`, the
    first free `...-2.mp4`, `...-3.mp4`, ... (an earlier video is never replaced silently)."""
    if is_path_file(path):
        path = Path(path).stem
    slug = re.sub(r"[^A-Za-z0-9_.-]+", "_", path).strip("._")[:60] or "path"
    base = Path(render_dir) / f"flythrough-{slug}-{mode}.mp4"
    if overwrite or not base.exists():
        return base
    n = 2
    while (cand := base.with_name(f"{base.stem}-{n}.mp4")).exists():
        n += 1
    return cand


@dataclass
class FlythroughResult:
    path: Path
    frames: int
    size: tuple[int, int]  # (H, W)
    seconds: float


def even_size(height: int, width: int) -> tuple[int, int]:
    """Round a frame size up to even numbers (yuv420p H.264 needs them)."""
    return int(height) + int(height) % 2, int(width) + int(width) % 2


def write_video(frames_rgb, out_path: Path, fps: float = 24.0, crf: int = CRF) -> int:
    """Write float RGB [H,W,3] frames in [0,1] (an iterable) as an H.264 mp4 (yuv420p,
    +faststart); returns the frame count. An odd-sized frame is padded by repeating its
    last row/column. The file appears only when complete."""
    from runfs.fsutil import atomic_write

    written = 0

    def encode(tmp: Path) -> None:
        nonlocal written
        written = _encode_h264(frames_rgb, tmp, fps, crf)

    atomic_write(Path(out_path), encode)  # a finished file only: an interrupted render leaves no half video
    return written


def _encode_h264(frames_rgb, path: Path, fps: float, crf: int) -> int:
    import imageio_ffmpeg

    writer = None
    n = 0
    try:
        for rgb in frames_rgb:
            arr = (np.clip(np.asarray(rgb, dtype=np.float32), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
            h, w = arr.shape[:2]
            if h % 2 or w % 2:
                arr = np.pad(arr, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge")
            if writer is None:
                size = (arr.shape[1], arr.shape[0])
                writer = imageio_ffmpeg.write_frames(
                    str(path), size, fps=float(fps), codec="libx264", pix_fmt_in="rgb24", pix_fmt_out="yuv420p",
                    macro_block_size=2, quality=None, ffmpeg_log_level="error",
                    output_params=["-crf", str(int(crf)), "-movflags", "+faststart"],
                )
                writer.send(None)
            elif (arr.shape[1], arr.shape[0]) != size:
                raise ValueError(f"frame {n} is {arr.shape[1]}x{arr.shape[0]}, the video {size[0]}x{size[1]}")
            writer.send(np.ascontiguousarray(arr))
            n += 1
        if writer is None:
            raise ValueError("no frames to write")
    finally:
        if writer is not None:
            writer.close()
    return n


def render_flythrough(g, poses: np.ndarray, camera, out_path: Path, fps: float = 24.0, backend=None,
                      track=None, background=None) -> FlythroughResult:
    from evaluation.model_io import render_pose

    t0 = time.perf_counter()
    seq = track(poses, "render: frames", total=len(poses)) if track else poses

    def frames():
        for pose in seq:
            yield render_pose(g, pose, camera, backend=backend, background=background).image

    n = write_video(frames(), out_path, fps)
    return FlythroughResult(Path(out_path), n, (int(camera.height), int(camera.width)), time.perf_counter() - t0)
