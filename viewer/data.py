"""What the viewer shows, read from a run folder as plain numpy (no viser here, so it tests alone).

World frame as everywhere (DESIGN.md): OpenCV-like, x right, y down, z forward, metres;
poses camera-to-world. Nothing is rotated for display: the viser scene's up direction is -y.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from runfs.errors import PanoError
from runfs.paths import RUN_MARKER, check_run_folder, default_run_folder, is_run_folder, open_run_folder

SH_C0 = 0.28209479177387814
MODEL_PATH = Path("train") / "point_cloud.ply"


@dataclass
class Target:
    """The run folder to show and the scene it was made from (None if that is gone)."""

    run_dir: Path
    scene: object | None  # schemas.scene.Scene


def resolve_target(path: Path, out: Path | None = None) -> Target:
    """SCENE (a folder holding scene.json; run folder `out` or runs/<scene-name>/, as `pano-pipe run`)
    or a run folder directly (its scene is the one its marker names, when that still loads)."""
    from schemas.scene_loader import load_scene

    path = Path(path)
    if (path / "scene.json").is_file():
        scene = load_scene(path, check_images=False)
        run_dir = Path(out) if out is not None else default_run_folder(scene.name, scene.root)
        if run_dir.is_dir():  # a run folder of another scene folder (a copy of the same name) is refused
            check_run_folder(run_dir, scene.root)
    elif path.is_dir() and is_run_folder(path):
        if out is not None and Path(out).resolve() != path.resolve():
            raise PanoError(out, f"--out given with a run folder ({path}); give one or the other")
        run_dir, scene = path, None
        try:
            marker = json.loads((path / RUN_MARKER).read_text())
            scene = load_scene(Path(marker["scene"]), check_images=False)
        except (OSError, ValueError, KeyError, TypeError, PanoError):
            scene = None  # cameras are then not shown; the model still is
    else:
        raise PanoError(path, "neither a scene folder (no scene.json) nor a pano-pipe run folder")
    if not run_dir.is_dir():
        raise PanoError(run_dir, f"no run folder; run `pano-pipe run all {path}` first")
    open_run_folder(run_dir)  # no symbolic link inside: the viewer reads the model and writes view/
    if not (run_dir / MODEL_PATH).is_file():
        raise PanoError(run_dir / MODEL_PATH, f"no trained model; run `pano-pipe run all {path}` first")
    if scene is not None:  # poses the run recovered (the poses stage) fill in what scene.json leaves out
        from pipeline.engine import complete_scene
        from pipeline.registry import build_registry

        scene = complete_scene(scene, run_dir, build_registry())
    return Target(run_dir, scene)


@dataclass
class Splats:
    centers: np.ndarray  # [N,3] float32
    covariances: np.ndarray  # [N,3,3] float32
    rgbs: np.ndarray  # [N,3] float32 in [0,1] (SH degree 0 only: viser shows no view dependence)
    opacities: np.ndarray  # [N,1] float32 in [0,1]

    def __len__(self) -> int:
        return len(self.centers)


def quat_to_matrix(wxyz: np.ndarray) -> np.ndarray:
    """[N,4] (w,x,y,z), not necessarily unit -> [N,3,3] rotation matrices."""
    q = np.asarray(wxyz, dtype=np.float64)
    q = q / np.maximum(np.linalg.norm(q, axis=-1, keepdims=True), 1e-12)
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    return np.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], axis=-1).reshape(-1, 3, 3)


def splats_from_model(g) -> Splats:
    """A `gaussians.Gaussians` as viser wants it: covariance R·S²·Rᵀ, colour 0.5 + C0·f_dc, sigmoid opacity."""
    import torch

    with torch.no_grad():
        means = g.means.detach().cpu().double().numpy()
        scales = torch.exp(g.log_scales.detach().cpu().double()).numpy()
        quats = g.quats.detach().cpu().double().numpy()
        dc = g.sh_dc.detach().cpu().double().numpy().reshape(len(means), 3)
        opac = torch.sigmoid(g.opacity_logits.detach().cpu().double()).numpy().reshape(-1, 1)
    rot = quat_to_matrix(quats)
    rs = rot * scales[:, None, :]  # R·S
    cov = rs @ rs.transpose(0, 2, 1)
    rgb = np.clip(0.5 + SH_C0 * dc, 0.0, 1.0)
    ok = np.isfinite(means).all(1) & np.isfinite(cov).all((1, 2)) & np.isfinite(opac[:, 0])
    return Splats(means[ok].astype(np.float32), cov[ok].astype(np.float32),
                  rgb[ok].astype(np.float32), opac[ok].astype(np.float32))


def floor_plan_segments(run_dir: Path) -> np.ndarray | None:
    """The union stage's rooms as line segments [M,2,3]: outline (and holes) at the floor and the
    ceiling, plus the vertical corners. None when the union stage has not run (or was skipped)."""
    from pipeline.engine import read_output

    union = read_output(run_dir, "union")
    if union is None:
        return None
    segs = []
    for room in union.rooms:
        fy, cy = room.floor_y, room.ceiling_y
        for ring in [room.polygon, *room.holes]:
            xz = np.asarray(ring, dtype=np.float64).reshape(-1, 2)
            if len(xz) < 2:
                continue
            nxt = np.roll(xz, -1, axis=0)
            for y in (fy, cy):
                a = np.column_stack([xz[:, 0], np.full(len(xz), y), xz[:, 1]])
                b = np.column_stack([nxt[:, 0], np.full(len(xz), y), nxt[:, 1]])
                segs.append(np.stack([a, b], axis=1))
            segs.append(np.stack([np.column_stack([xz[:, 0], np.full(len(xz), fy), xz[:, 1]]),
                                  np.column_stack([xz[:, 0], np.full(len(xz), cy), xz[:, 1]])], axis=1))
    return np.concatenate(segs).astype(np.float32) if segs else None


def layout_cloud(run_dir: Path, max_points: int = 200_000) -> tuple[np.ndarray, np.ndarray] | None:
    """The sampling stage's point cloud (points [N,3], colours uint8 [N,3]), subsampled to
    `max_points`; None when that stage has not run."""
    from stages.cloud_io import read_cloud

    folder = Path(run_dir) / "sampling"
    if not (folder / "cloud.npz").is_file():
        return None
    try:
        cloud = read_cloud(folder)
    except PanoError:
        return None
    pts, col = cloud["points"], cloud["colors"]
    if len(pts) > max_points:
        keep = np.random.default_rng(0).choice(len(pts), max_points, replace=False)
        pts, col = pts[keep], col[keep]
    col = np.asarray(col)
    if col.dtype != np.uint8:
        col = (np.clip(col, 0.0, 1.0) * 255 + 0.5).astype(np.uint8)
    return np.asarray(pts, dtype=np.float32), col


@dataclass
class CameraView:
    name: str
    split: str  # "train" or "test"
    c2w: np.ndarray  # [4,4]


def scene_cameras(scene) -> list[CameraView]:
    """Every view of the scene (train and test) with its pose."""
    if scene is None:
        return []
    return [CameraView(v.name, v.split, np.asarray(v.pose_matrix, dtype=np.float64)) for v in scene.views]


def level_pose(c2w: np.ndarray) -> np.ndarray:
    """The same position, turned to look horizontally along the yaw of c2w's forward (z) axis, y down:
    the pose a panorama is rendered from (level, like the captured ones)."""
    c2w = np.asarray(c2w, dtype=np.float64)
    fwd = c2w[:3, 2].copy()
    fwd[1] = 0.0
    n = np.linalg.norm(fwd)
    if n < 1e-6:  # looking straight up or down: take the camera's own down-screen direction
        fwd = c2w[:3, 1].copy() * np.sign(c2w[1, 2] or 1.0)
        fwd[1] = 0.0
        n = np.linalg.norm(fwd)
        if n < 1e-6:
            fwd, n = np.array([0.0, 0.0, 1.0]), 1.0
    z = fwd / n
    y = np.array([0.0, 1.0, 0.0])
    x = np.cross(y, z)
    out = np.eye(4)
    out[:3, 0], out[:3, 1], out[:3, 2], out[:3, 3] = x, y, z, c2w[:3, 3]
    return out


def look_along_room(position: np.ndarray, centers: np.ndarray, bins: int = 36, band_m: float = 0.5,
                    min_points: int = 20) -> np.ndarray:
    """The level direction (unit, y = 0) from `position` along which the room runs farthest: the
    splat centres within `band_m` of the camera's height, binned by azimuth around it, and the
    bin with the largest median distance (a median, so a few floaters beyond a wall do not count).
    Falls back to +z when too few centres lie in that band."""
    p = np.asarray(position, dtype=np.float64)
    c = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    near = c[np.abs(c[:, 1] - p[1]) < band_m] - p
    if len(near) < min_points:
        return np.array([0.0, 0.0, 1.0])
    azimuth = np.arctan2(near[:, 0], near[:, 2])
    dist = np.hypot(near[:, 0], near[:, 2])
    idx = np.minimum(((azimuth + np.pi) / (2 * np.pi) * bins).astype(int), bins - 1)
    medians = np.full(bins, -1.0)
    for b in range(bins):
        d = dist[idx == b]
        if len(d) >= 3:
            medians[b] = float(np.median(d))
    best = (int(np.argmax(medians)) + 0.5) / bins * 2 * np.pi - np.pi
    return np.array([np.sin(best), 0.0, np.cos(best)])
