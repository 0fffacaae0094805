"""From SfM's arbitrary frame to pano-pipe's world: upright, metric, placed.

SfM recovers poses up to a similarity (rotation, translation, scale). Two ways
fix it (docs/poses.md):

- No view has a known pose: gravity is the cameras' mean down axis (360°
  cameras are levelled, so each camera's +y is close to gravity and their
  mean closer still); the scale makes the cameras' heights over the floor
  plane, fitted to the sparse points below them, equal the known heights; the
  first view sits at the origin looking along +z.
- Some views have known poses: they fix the frame by a similarity fit
  (rotation from their orientations, scale and translation from their
  centres; with one known view the scale comes from the floor as above), and
  the fit's residuals are reported.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

#: A floor plane's normal may lean this far from the cameras' mean down axis.
MAX_FLOOR_TILT_DEG = 10.0
RANSAC_TRIALS = 500


@dataclass
class Similarity:
    """x -> scale * rotation @ x + translation (SfM frame to world)."""

    scale: float
    rotation: np.ndarray
    translation: np.ndarray

    def points(self, x: np.ndarray) -> np.ndarray:
        return self.scale * np.asarray(x) @ self.rotation.T + self.translation

    def pose(self, cam_to_world: np.ndarray) -> np.ndarray:
        """A camera-to-world pose of the SfM frame as one of the world (scale leaves rotations alone)."""
        out = np.eye(4)
        out[:3, :3] = self.rotation @ cam_to_world[:3, :3]
        out[:3, 3] = self.points(cam_to_world[:3, 3])
        return out


@dataclass
class Floor:
    """A plane n.x + d = 0 (n unit, pointing down, into the floor) in the upright SfM frame."""

    normal: np.ndarray
    offset: float
    inliers: int
    residual: float  # RMS distance of the inliers to the plane
    #: standard uncertainty of the offset where it is measured otherwise (sfm.floor_boundary);
    #: None: the plane fit's, residual / sqrt(inliers)
    offset_sd: float | None = None

    def height_above(self, x: np.ndarray) -> np.ndarray:
        return -(np.asarray(x) @ self.normal + self.offset)

    @property
    def offset_uncertainty(self) -> float:
        return self.residual / np.sqrt(self.inliers) if self.offset_sd is None else self.offset_sd


@dataclass
class Alignment:
    transform: Similarity
    #: relative standard uncertainty of the scale (0.01 = 1 %); None: no scale was found
    scale_uncertainty: float | None
    #: what fixed the frame: "floor", "known poses", "known pose and floor", "known pose" (one given
    #: view, no scale), "given scale" or "gravity" (upright only, no scale)
    source: str
    floor: Floor | None = None
    floor_tilt_deg: float | None = None
    #: known views only: distance (m) and angle (degrees) between the fitted and the given pose
    residual_m: dict[str, float] = field(default_factory=dict)
    residual_deg: dict[str, float] = field(default_factory=dict)
    #: each placed camera's height over the fitted floor (metres); empty when no floor was fitted
    camera_heights: dict[str, float] = field(default_factory=dict)
    #: where the scale came from: FLOOR_PLANE, FLOOR_WALL_BOUNDARY, KNOWN_POSES, GIVEN_SCALE or NO_SCALE
    scale_source: str = "floor_plane"


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation taking unit vector a to unit vector b."""
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    v, c = np.cross(a, b), float(a @ b)
    if c < -1 + 1e-12:  # opposite: half a turn about any axis normal to a
        axis = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
        axis /= np.linalg.norm(axis)
        return 2.0 * np.outer(axis, axis) - np.eye(3)
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


def nearest_rotation(m: np.ndarray) -> np.ndarray:
    u, _, vt = np.linalg.svd(m)
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt


def rotation_angle_deg(r: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0))))


def upright_rotation(cam_to_world: list[np.ndarray]) -> np.ndarray:
    """Rotation of the SfM frame that takes the cameras' mean down axis (their +y) to +y and turns
    the first camera's forward axis towards +z about it."""
    down = np.mean([p[:3, 1] for p in cam_to_world], axis=0)
    level = rotation_between(down, np.array([0.0, 1.0, 0.0]))
    forward = level @ cam_to_world[0][:3, 2]
    yaw = np.arctan2(forward[0], forward[2])
    c, s = np.cos(-yaw), np.sin(-yaw)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]) @ level


def fit_floor(points: np.ndarray, centres: np.ndarray, seed: int = 0, min_depression_deg: float = 0.0
              ) -> Floor | None:
    """The plane under the cameras holding the most points, its normal within MAX_FLOOR_TILT_DEG of
    +y, in an upright frame, with (almost) nothing under it; None when no such plane is found. With
    `min_depression_deg`, only points seen at least that far below the horizon from the nearest
    camera count: a dense cloud's wall points at the cameras' own height form a horizontal band
    under them that can outnumber the floor's points.

    Nothing lies under a floor: a plane with more than MAX_POINTS_UNDER_FLOOR of its own inliers
    clearly under it is a table top, a bed or a band of furniture tops (on a plain floor, where SfM
    finds no floor point, the densest horizontal plane under the cameras is such a one), and the
    plane is looked for again among the points under it."""
    below = points[points[:, 1] > centres[:, 1].max()]
    if min_depression_deg > 0 and len(below):
        horizontal = np.min(np.linalg.norm(below[:, None, [0, 2]] - centres[None, :, [0, 2]], axis=2), axis=1)
        drop = below[:, 1] - centres[:, 1].max()
        below = below[np.degrees(np.arctan2(drop, horizontal)) >= min_depression_deg]
    if len(below) < 10:
        return None
    # inlier band: 1 % of the typical camera-to-point distance (the frame has no unit yet)
    spread = float(np.median(np.linalg.norm(below - centres.mean(axis=0), axis=1)))
    band = 0.01 * spread
    rng = np.random.default_rng(seed)
    candidates = below
    for _ in range(FLOOR_TRIES):
        floor = _plane(candidates, band, rng)
        if floor is None:
            return None
        depth = below @ floor.normal + floor.offset  # > 0: under the plane
        if np.sum(depth > 3 * band) <= max(MAX_POINTS_UNDER_FLOOR * floor.inliers, POINTS_UNDER_ANY_FLOOR):
            return floor
        candidates = below[depth > band]
    return None


#: A floor plane may have at most this share of its inliers' count of points clearly (3 inlier
#: bands) under it, or POINTS_UNDER_ANY_FLOOR (stray points, reflections); measured: 2.5 % under a
#: textured simulated floor, 3 under zind_pair's 15 floor inliers; 46 % under openmvg_flat's bed,
#: 530 % under the furniture tops a plain simulated floor leaves as the densest plane (docs/poses.md).
MAX_POINTS_UNDER_FLOOR = 0.25
POINTS_UNDER_ANY_FLOOR = 5
#: Planes tried, each among the points under the one before.
FLOOR_TRIES = 3


def _plane(points: np.ndarray, band: float, rng: np.random.Generator) -> Floor | None:
    """RANSAC: the plane within MAX_FLOOR_TILT_DEG of level holding the most of `points` within
    `band`, refined by least squares; None below 10 inliers."""
    if len(points) < 10:
        return None
    best, best_count = None, 0
    max_tilt = np.cos(np.radians(MAX_FLOOR_TILT_DEG))
    for _ in range(RANSAC_TRIALS):
        a, b, c = points[rng.choice(len(points), 3, replace=False)]
        n = np.cross(b - a, c - a)
        norm = np.linalg.norm(n)
        if norm == 0:
            continue
        n = n / norm * np.sign(n[1] or 1.0)
        if n[1] < max_tilt:
            continue
        count = int(np.sum(np.abs((points - a) @ n) < band))
        if count > best_count:
            best, best_count = (n, a), count
    if best is None or best_count < 10:
        return None
    n, a = best
    inliers = points[np.abs((points - a) @ n) < band]
    # least-squares refinement: the normal is the direction of least spread of the inliers
    centre = inliers.mean(axis=0)
    n = np.linalg.svd(inliers - centre)[2][2]
    n = n * np.sign(n[1])
    residual = float(np.sqrt(np.mean(((inliers - centre) @ n) ** 2)))
    return Floor(n, float(-centre @ n), len(inliers), residual)


def metric_scale(heights_sfm: np.ndarray, heights_m: np.ndarray, floor: Floor) -> tuple[float, float]:
    """Scale s minimising sum (s d_i - h_i)^2 over the cameras' SfM heights d_i and known heights
    h_i, and its relative standard uncertainty: the spread of the per-camera ratios h_i / d_i
    (over sqrt n) combined with the floor plane's own uncertainty over the mean height."""
    d, h = np.asarray(heights_sfm, float), np.asarray(heights_m, float)
    s = float(d @ h / (d @ d))
    ratios = h / d
    n = len(d)
    spread = float(np.std(ratios, ddof=1) / np.sqrt(n)) / s if n > 1 else 0.0
    plane = floor.offset_uncertainty / float(np.mean(d))
    return s, float(np.hypot(spread, plane))


#: Where the metric scale came from (PosesOutput.scale_source): a plane fitted to the sparse points
#: under the cameras, the floor level at which the floor–wall boundaries show in the panoramas
#: (sfm.floor_boundary), the views with given poses, a scale given outright, or nothing (the poses
#: are kept up to scale).
FLOOR_PLANE, FLOOR_WALL_BOUNDARY, KNOWN_POSES, GIVEN_SCALE, NO_SCALE = (
    "floor_plane", "floor_wall_boundary", "known_poses", "given_scale", "none")

#: A floor cue after the plane fit: (upright camera-to-world poses, upright points) -> a level
#: floor in that frame, or None.
FloorCue = Callable[[dict[str, np.ndarray], np.ndarray], Floor | None]


def align_to_floor(cam_to_world: dict[str, np.ndarray], points: np.ndarray, heights: dict[str, float],
                   order: list[str], scale: float | None = None, min_depression_deg: float = 0.0,
                   cues: Sequence[tuple[str, FloorCue]] = (), unscaled: bool = False) -> Alignment:
    """Upright and metric alignment without known poses; `order` puts the view that defines the
    origin and the forward axis first. The scale puts the cameras `heights` over the floor: the
    plane fitted to the points, else the first of `cues` (name, cue) that finds one; or it is the
    given `scale` (the floor, where found, is then only measured). With no floor, `unscaled` keeps
    the SfM frame's unit (scale 1, scale_source "none"); else ValueError."""
    names = [v for v in order if v in cam_to_world]
    up = upright_rotation([cam_to_world[v] for v in names])
    centres = np.array([cam_to_world[v][:3, 3] for v in names]) @ up.T
    upright_points = points @ up.T
    floor = fit_floor(upright_points, centres, min_depression_deg=min_depression_deg)
    tilt = None if floor is None else rotation_angle_deg(rotation_between(floor.normal, np.array([0.0, 1.0, 0.0])))
    if scale is not None:
        measured = {} if floor is None else dict(zip(names, (scale * floor.height_above(centres)).tolist()))
        return Alignment(Similarity(scale, up, -scale * centres[0]), 0.0, "given scale", floor=floor,
                         floor_tilt_deg=tilt, camera_heights=measured, scale_source=GIVEN_SCALE)
    source = FLOOR_PLANE
    if floor is None and cues:
        upright = {}
        for v in names:
            pose = np.eye(4)
            pose[:3, :3], pose[:3, 3] = up @ cam_to_world[v][:3, :3], up @ cam_to_world[v][:3, 3]
            upright[v] = pose
        for source, cue in cues:
            floor = cue(upright, upright_points)
            if floor is not None:
                break
    if floor is None:
        if unscaled:
            return Alignment(Similarity(1.0, up, -centres[0]), None, "gravity", scale_source=NO_SCALE)
        raise ValueError("no floor plane among the sparse points below the cameras"
                         + (" and no floor–wall boundary in the panoramas" if cues else "") + ", so no metric scale")
    d = floor.height_above(centres)
    if np.any(d <= 0):
        raise ValueError("the fitted floor plane is not below every camera")
    scale, uncertainty = metric_scale(d, np.array([heights[v] for v in names]), floor)
    transform = Similarity(scale, up, -scale * centres[0])
    return Alignment(transform, uncertainty, "floor", floor=floor, floor_tilt_deg=tilt,
                     camera_heights=dict(zip(names, (scale * d).tolist())), scale_source=source)


def align_to_known(cam_to_world: dict[str, np.ndarray], known: dict[str, np.ndarray], points: np.ndarray,
                   heights: dict[str, float], order: list[str], cues: Sequence[tuple[str, FloorCue]] = (),
                   unscaled: bool = False) -> Alignment:
    """Similarity fit to the views with known camera-to-world poses (at least one registered); with
    one, the scale as align_to_floor finds it (`cues`, `unscaled`)."""
    names = [v for v in order if v in known and v in cam_to_world]
    # rotation: the chordal mean of world_from_sfm over the known views
    rotation = nearest_rotation(sum(known[v][:3, :3] @ cam_to_world[v][:3, :3].T for v in names))
    src = np.array([cam_to_world[v][:3, 3] for v in names]) @ rotation.T
    dst = np.array([known[v][:3, 3] for v in names])
    src_c, dst_c = src - src.mean(axis=0), dst - dst.mean(axis=0)
    uncertainty, floor, source, camera_heights, scale_source = 0.0, None, "known poses", {}, KNOWN_POSES
    if len(names) >= 2 and np.linalg.norm(src_c) > 0 and np.linalg.norm(dst_c) > 0:
        scale = float(np.sum(src_c * dst_c) / np.sum(src_c * src_c))
        if not scale > 0:  # the given positions are the recovered ones mirrored: no rigid world fits
            raise ValueError(f"the given poses contradict structure from motion: their positions fit the "
                             f"recovered ones only mirrored (scale {scale:.3g}); check the poses of "
                             f"{', '.join(names[:4])}")
        residual = dst_c - scale * src_c
        uncertainty = float(np.sqrt(np.sum(residual ** 2) / max(len(names) - 1, 1)) / np.linalg.norm(dst_c))
    else:  # one known view: its pose fixes rotation and position, the floor the scale
        floor_fit = align_to_floor(cam_to_world, points, heights, order, cues=cues, unscaled=unscaled)
        scale, uncertainty, floor = floor_fit.transform.scale, floor_fit.scale_uncertainty, floor_fit.floor
        source = "known pose" if floor is None else "known pose and floor"
        camera_heights, scale_source = floor_fit.camera_heights, floor_fit.scale_source
    transform = Similarity(scale, rotation, dst.mean(axis=0) - scale * src.mean(axis=0))
    res_m, res_deg = {}, {}
    for v in names:
        fitted = transform.pose(cam_to_world[v])
        res_m[v] = float(np.linalg.norm(fitted[:3, 3] - known[v][:3, 3]))
        res_deg[v] = rotation_angle_deg(fitted[:3, :3].T @ known[v][:3, :3])
    return Alignment(transform, uncertainty, source, floor=floor, residual_m=res_m, residual_deg=res_deg,
                     camera_heights=camera_heights, scale_source=scale_source)


def pose_errors(recovered: dict[str, np.ndarray], truth: dict[str, np.ndarray]) -> dict[str, tuple[float, float]]:
    """Per view: (position error in metres, rotation error in degrees) of camera-to-world poses after
    the rigid motion that best aligns `recovered` to `truth` (no scale: a metric recovery must get
    the scale itself). A scene posed from its panoramas alone is only defined up to that motion."""
    names = [v for v in recovered if v in truth]
    rotation = nearest_rotation(sum(truth[v][:3, :3] @ recovered[v][:3, :3].T for v in names))
    src = np.array([rotation @ recovered[v][:3, 3] for v in names])
    offset = np.array([truth[v][:3, 3] for v in names]).mean(axis=0) - src.mean(axis=0)
    return {v: (float(np.linalg.norm(s + offset - truth[v][:3, 3])),
                rotation_angle_deg((rotation @ recovered[v][:3, :3]).T @ truth[v][:3, :3]))
            for v, s in zip(names, src)}
