"""Manhattan alignment of a panorama: the rotation that makes gravity vertical and the walls
run along the image axes, as HorizonNet's training panoramas are (its preprocess.py).

1. Line segments: the panorama is resampled into ten perspective views (eight around the
   horizon, one up, one down; 90° field of view, overlapping by half), OpenCV's line segment
   detector runs on each, and every segment becomes the unit normal n of its great circle
   (the plane through the camera and the segment) with its length as weight.
2. Gravity: given (the pose's down axis), or the vanishing direction of vertical lines: RANSAC
   over pairs of near-vertical segments (v = n_i x n_j, within `max_tilt_deg` of the image's
   vertical), scored by the summed length of segments whose great circle passes within 1° of v.
3. Yaw: every non-vertical segment votes for the horizontal direction it vanishes to,
   v = g x n; Manhattan walls put the votes at two directions 90° apart, found as the peak of a
   kernel density of the votes modulo 90°.
4. Refinement: robust least squares (scipy, soft-L1) of n·a_k over the segments assigned to each
   axis a_k of the frame: all three rotation angles, or only the yaw when gravity was given.

The aligned frame's yaw is chosen among the four Manhattan-equivalent ones as the one closest
to the view's own (|yaw| <= 45°), so an already aligned panorama stays as it is.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from panogeom.equirect import angles_to_dirs, angles_to_pixel, column_longitudes, dirs_to_angles
from panogeom.rotate import level_rotation, rotate_equirect, yaw_matrix, yaw_tilt_deg

__all__ = ["Alignment", "line_segments", "estimate_alignment", "align_panorama", "boundaries_to_view",
           "room_in_view"]

#: Perspective views for the line detector: (yaw, pitch) in degrees, 90° field of view each.
VIEWS = [(float(a), 0.0) for a in range(0, 360, 45)] + [(0.0, 90.0), (0.0, -90.0)]
VIEW_FOV_DEG = 90.0
Y = np.array([0.0, 1.0, 0.0])
#: Fewer segments than this agreeing with the frame: the panorama is left as it is.
MIN_INLIERS = 12
#: A rotation under half a pixel of HorizonNet's 1024-wide input is not applied: resampling would
#: cost more sharpness than the turn gains.
MIN_APPLIED_DEG = 0.5 * 360.0 / 1024


@dataclass
class Alignment:
    """d_aligned = rotation @ d_view: the view's directions in the room's (Manhattan) frame."""

    rotation: np.ndarray
    gravity: str  # "pose": given; "lines": estimated; "none": too few lines, left level
    segments: int  # segments detected
    inliers: int  # segments that agree with one of the three axes
    notes: list[str] = field(default_factory=list)

    @property
    def yaw_deg(self) -> float:
        return yaw_tilt_deg(self.rotation)[0]

    @property
    def tilt_deg(self) -> float:
        return yaw_tilt_deg(self.rotation)[1]

    @property
    def angle_deg(self) -> float:
        """The whole rotation's angle."""
        from scipy.spatial.transform import Rotation

        return float(np.degrees(Rotation.from_matrix(self.rotation).magnitude()))


def _view_rotation(yaw_deg: float, pitch_deg: float) -> np.ndarray:
    """Perspective-view-to-panorama rotation: the view looks along +z turned by yaw, then pitched up."""
    p = np.radians(pitch_deg)
    c, s = np.cos(p), np.sin(p)
    pitch = np.array([[1.0, 0.0, 0.0], [0.0, c, s], [0.0, -s, c]])  # +pitch turns +z towards -y (up)
    return yaw_matrix(np.radians(yaw_deg)) @ pitch


def line_segments(gray: np.ndarray, view_size: int | None = None, min_length: float | None = None
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Great-circle normals [N,3] (unit, panorama frame) and weights [N] (segment length in
    view pixels) of the straight line segments of an equirectangular grey image (uint8)."""
    h, w = gray.shape
    size = view_size or max(64, w // 4)
    min_length = min_length if min_length is not None else size / 16.0
    f = (size / 2.0) / np.tan(np.radians(VIEW_FOV_DEG) / 2.0)
    c = (np.arange(size) + 0.5 - size / 2.0) / f
    gx, gy = np.meshgrid(c, c)
    local = np.stack([gx, gy, np.ones_like(gx)], -1)
    padded = np.concatenate([gray[:, -2:], gray, gray[:, :2]], axis=1)
    lsd = cv2.createLineSegmentDetector(cv2.LSD_REFINE_STD)
    normals, weights = [], []
    for yaw, pitch in VIEWS:
        R = _view_rotation(yaw, pitch)
        col, row = angles_to_pixel(*dirs_to_angles(local @ R.T), h, w)
        view = cv2.remap(padded, (col + 2).astype(np.float32), row.astype(np.float32), cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REPLICATE)
        found = lsd.detect(view)[0]
        if found is None:
            continue
        seg = found.reshape(-1, 4).astype(np.float64)
        length = np.hypot(seg[:, 2] - seg[:, 0], seg[:, 3] - seg[:, 1])
        seg, length = seg[length >= min_length], length[length >= min_length]
        if not len(seg):
            continue
        # pixel (x, y) of the view (centres at +0.5) -> ray in the view frame -> panorama frame
        p1 = np.stack([(seg[:, 0] - size / 2.0) / f, (seg[:, 1] - size / 2.0) / f, np.ones(len(seg))], 1)
        p2 = np.stack([(seg[:, 2] - size / 2.0) / f, (seg[:, 3] - size / 2.0) / f, np.ones(len(seg))], 1)
        n = np.cross(p1 @ R.T, p2 @ R.T)
        normals.append(n / np.linalg.norm(n, axis=1, keepdims=True))
        weights.append(length)
    if not normals:
        return np.zeros((0, 3)), np.zeros(0)
    return np.concatenate(normals), np.concatenate(weights)


def _gravity_from_lines(n: np.ndarray, w: np.ndarray, max_tilt_deg: float, rng: np.random.Generator,
                        iterations: int = 400) -> np.ndarray | None:
    """The vertical vanishing direction (pointing down, +y-ish) or None when no consensus."""
    cand = np.flatnonzero(np.abs(n @ Y) < np.sin(np.radians(max_tilt_deg)))  # could be vertical lines
    if len(cand) < 2:
        return None
    tol = np.sin(np.radians(1.0))
    best, best_score = None, 0.0
    for _ in range(iterations):
        i, j = rng.choice(cand, 2, replace=False)
        v = np.cross(n[i], n[j])
        norm = np.linalg.norm(v)
        if norm < 1e-6:
            continue
        v = v / norm * np.sign(v[1] or 1.0)
        if v[1] < np.cos(np.radians(max_tilt_deg)):
            continue
        score = w[np.abs(n @ v) < tol].sum()
        if score > best_score:
            best, best_score = v, score
    if best is None:
        return None
    for deg in (1.0, 0.5):  # refine: the direction most orthogonal to the inliers' normals
        m = np.abs(n @ best) < np.sin(np.radians(deg))
        if m.sum() < 2:
            break
        evals, evecs = np.linalg.eigh((n[m] * w[m, None]).T @ n[m])
        best = evecs[:, 0] * np.sign(evecs[1, 0] or 1.0)
    return best


def _yaw_from_lines(n: np.ndarray, w: np.ndarray, down: np.ndarray) -> tuple[float, bool]:
    """Longitude (radians, in [-45°, 45°)) of the Manhattan walls' direction in the levelled frame."""
    L = level_rotation(down)
    nl = n @ L.T  # normals in the levelled frame
    keep = np.abs(nl[:, 1]) > np.sin(np.radians(2.0))  # vertical lines say nothing about the yaw
    if keep.sum() < 4:
        return 0.0, False
    v = np.cross(Y, nl[keep])  # horizontal vanishing directions (x, 0, z)
    angle = np.arctan2(v[:, 0], v[:, 2])  # longitude of each vote
    wk = w[keep]
    grid = np.radians(np.arange(-45.0, 45.0, 0.1))
    diff = np.angle(np.exp(4j * (angle[None, :] - grid[:, None]))) / 4.0  # distance modulo 90°
    density = (wk[None, :] * np.exp(-0.5 * (diff / np.radians(1.0)) ** 2)).sum(1)
    yaw = float(grid[np.argmax(density)])
    near = np.abs(np.angle(np.exp(4j * (angle - yaw))) / 4.0) < np.radians(2.0)
    if near.sum() >= 2:  # the weighted circular mean of the votes near the peak
        yaw = float(np.angle((wk[near] * np.exp(4j * angle[near])).sum()) / 4.0)
    return yaw, True


def _refine(R: np.ndarray, n: np.ndarray, w: np.ndarray, yaw_only: bool) -> tuple[np.ndarray, int]:
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    tol = np.sin(np.radians(2.0))
    for _ in range(2):
        dots = np.abs(n @ R.T)  # [N,3]: the rows of R are the frame's axes in the view frame
        axis = np.argmin(dots, axis=1)
        m = dots[np.arange(len(n)), axis] < tol
        if m.sum() < 3:
            return R, int(m.sum())
        nm, wm, am = n[m], np.sqrt(w[m]), axis[m]

        def residuals(p, R0=R):
            Rp = (yaw_matrix(p[0]) if yaw_only else Rotation.from_rotvec(p).as_matrix()) @ R0
            return wm * np.einsum("ij,ij->i", nm, Rp[am])

        x0 = np.zeros(1 if yaw_only else 3)
        sol = least_squares(residuals, x0, loss="soft_l1", f_scale=np.sin(np.radians(0.5)) * wm.mean())
        R = (yaw_matrix(sol.x[0]) if yaw_only else Rotation.from_rotvec(sol.x).as_matrix()) @ R
    return R, int(m.sum())


def _canonical_yaw(R: np.ndarray) -> np.ndarray:
    """Among the four Manhattan-equivalent frames (turns of 90° about gravity), the one with
    |yaw| <= 45°."""
    yaw = np.radians(yaw_tilt_deg(R)[0])
    k = np.round(yaw / (np.pi / 2))
    return yaw_matrix(-k * np.pi / 2) @ R


def estimate_alignment(rgb: np.ndarray, down: np.ndarray | None = None, max_tilt_deg: float = 30.0,
                       seed: int = 0) -> Alignment:
    """The rotation into the room's Manhattan frame of an equirectangular RGB panorama ([H,W,3],
    float in [0,1] or uint8). `down`: gravity in the view's frame where known (only the yaw is then
    estimated)."""
    img = np.asarray(rgb)
    if img.dtype != np.uint8:
        img = (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    if img.shape[1] > 2048:
        img = cv2.resize(img, (2048, 1024), interpolation=cv2.INTER_AREA)
    gray = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY) if img.ndim == 3 else img
    n, w = line_segments(gray)
    notes: list[str] = []
    source = "pose"
    if down is None:
        source = "lines"
        down = _gravity_from_lines(n, w, max_tilt_deg, np.random.default_rng(seed))
        if down is None:
            notes.append("no vertical lines found: gravity assumed along the image's vertical")
            source, down = "none", Y
    else:
        down = np.asarray(down, dtype=np.float64) / np.linalg.norm(down)
    yaw, ok = _yaw_from_lines(n, w, down)
    if not ok:
        notes.append("too few horizontal lines for the walls' direction: yaw left at 0")
    R = yaw_matrix(-yaw) @ level_rotation(down)  # turn the walls' direction onto the axes
    inliers = 0
    if ok and source != "none":
        R, inliers = _refine(R, n, w, yaw_only=source == "pose")
        if inliers < MIN_INLIERS:
            notes.append(f"only {inliers} line segments agree with a Manhattan frame: panorama left as it is"
                         + (" (levelled by the pose's gravity)" if source == "pose" else ""))
            R = level_rotation(down) if source == "pose" else np.eye(3)
            source = "pose" if source == "pose" else "none"
    return Alignment(_canonical_yaw(R), source, len(n), inliers, notes)


def align_panorama(rgb: np.ndarray, alignment: Alignment, size: tuple[int, int] | None = None) -> np.ndarray:
    """The panorama in the room's frame (what HorizonNet expects)."""
    return rotate_equirect(rgb, alignment.rotation, size=size)


def boundaries_to_view(bounds: np.ndarray, rotation: np.ndarray, width: int,
                       values: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None]:
    """Boundaries found in the aligned panorama ([K,W'] latitudes, one per aligned column) as the
    view's own image sees them: [K,width] latitudes per view column. Each boundary point is turned
    back into the view's frame (Rᵀ d) and its latitude interpolated at the view's column
    longitudes (periodically). `values` ([W'], e.g. a confidence) follow the first row's points."""
    b = np.asarray(bounds, dtype=np.float64)
    R = np.asarray(rotation, dtype=np.float64)
    phi_a = column_longitudes(b.shape[1])
    phi_v = column_longitudes(width)
    out = np.empty((b.shape[0], width))
    mapped = None
    for i, row in enumerate(b):
        phi, theta = dirs_to_angles(angles_to_dirs(phi_a, row) @ R)  # rows: Rᵀ d
        order = np.argsort(phi)
        phi, theta = phi[order], theta[order]
        xs = np.concatenate([phi[-1:] - 2 * np.pi, phi, phi[:1] + 2 * np.pi])
        out[i] = np.interp(phi_v, xs, np.concatenate([theta[-1:], theta, theta[:1]]))
        if i == 0 and values is not None:
            v = np.asarray(values, dtype=np.float64)[order]
            mapped = np.interp(phi_v, xs, np.concatenate([v[-1:], v, v[:1]]))
    return out, mapped


def room_in_view(room, raw: np.ndarray, rotation: np.ndarray, width: int):
    """A room fitted on the aligned panorama, turned back into the view's own frame:
    (room with the floor corners' (x, z) in the view's frame, its boundaries [2,width] as the
    view's image sees them, the model's raw boundaries [2,W'] likewise, the per-column
    confidence [width]). Heights stay distances along gravity."""
    from layoutnet import postprocess as pp

    R = np.asarray(rotation, dtype=np.float64)
    h, c = room.camera_height, room.ceiling_distance
    fitted_raw_width = pp.polygon_to_boundaries(room.polygon, h, c, raw.shape[1])
    conf_aligned = pp.column_confidence(raw, fitted_raw_width)
    dense = pp.polygon_to_boundaries(room.polygon, h, c, max(2048, 2 * width))
    fitted, _ = boundaries_to_view(dense, R, width)
    _, conf = boundaries_to_view(fitted_raw_width, R, width, values=conf_aligned)
    raw_view, _ = boundaries_to_view(raw, R, raw.shape[1])
    corners = np.stack([room.polygon[:, 0], np.full(len(room.polygon), h), room.polygon[:, 1]], 1)
    turned = corners @ R  # Rᵀ p per row: the floor corners in the view's frame
    view_room = pp.RoomLayout(turned[:, [0, 2]], h, c, room.method, list(room.notes))
    return view_room, fitted, raw_view, conf
