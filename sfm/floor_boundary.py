"""The floor level from where the floor meets the walls: a metric cue that a plain floor still gives.

A plain wooden or carpeted floor gives structure from motion (almost) no point, so no floor plane
can be fitted to the sparse points (sfm.frame.fit_floor). But every vertical surface standing on
the floor (walls, cupboards, the front of a sofa) meets it along a line that the panoramas show
as an edge, the floor–wall boundary, and the sparse points on those surfaces are there. For a
point P on such a surface, its foot (P dropped vertically onto the floor) lies on that line: seen
from a camera h units above the floor at horizontal distance D from P, it is at the depression
atan(h / D). One unknown fixes every foot in every panorama at once: the floor's level y_f in the
upright SfM frame (y down).

For each level on a grid, the foot of every point is projected into each panorama that observes
the point, and the vertical intensity gradient of the panorama there (smoothed, averaged over a
degree of longitude) is read; the level at which the feet land on edges in all the panoramas at
once is the floor. Points on the ceiling, on a table top or on a wall hidden behind furniture put
their feet on no edge in particular: they raise the background, which a running median over the
levels takes off. The camera heights over that level, with the heights the user gave, give the
metric scale (sfm.frame.metric_scale), exactly as a fitted floor plane does.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.ndimage import median_filter

from panogeom.resample import remap_equirect
from sfm.frame import Floor, FloorCue
from sfm.records import Panorama

#: The panorama is smoothed by a Gaussian of this many degrees (at least a pixel) before its vertical
#: gradient is taken: a boundary is an edge at that scale, the fine texture of the surfaces is not.
EDGE_SIGMA_DEG = 0.7
#: Longitudes averaged around a foot (degrees): a boundary is an edge along the wall, noise is not.
COLUMN_WINDOW_DEG = 1.0
#: Pixels next to a mask's edge (tripod, nadir cap) are not read: the mask's own edge is no boundary.
MASK_MARGIN_PX = 3
#: A foot counts only this far (degrees, seen from the camera) from its point: nearer, it lands
#: on the point's own texture, which made it a feature, and every level just under a band of
#: points would look like a floor.
MIN_FOOT_SEPARATION_DEG = 5.0
#: Points seen more than this far above or below the horizon are left out: at such angles they
#: are on the ceiling or floor near the camera, not on a wall.
MAX_ELEVATION_DEG = 60.0
#: The levels searched: camera heights from 2 % to 4x the median horizontal camera-to-point
#: distance (depressions of the median foot from about 1° to 76°), on a logarithmic grid.
HEIGHT_RANGE = (0.02, 4.0)
COARSE_STEP = 0.01  # relative
FINE_STEP = 0.0005
#: The coarse search reads this many observations at most (a random subset, spread over the views).
COARSE_OBSERVATIONS = 4000
#: The background of the score: its running median over this relative span of levels.
BACKGROUND_SPAN = 0.5
#: A level is the floor only if its excess edge strength stands this many robust standard
#: deviations above the others' (its contrast).
MIN_CONTRAST = 6.0
#: The floor is searched no deeper under the cameras than this many times the depth of the lowest
#: points (this percentile of the observed points' depths under the lowest camera): a real floor
#: lies just under the lowest points of its walls and furniture (measured: 1.0x on a textured
#: simulated floor, 1.2x on a plain one, 1.0x on openmvg_flat).
LOWEST_POINTS_PERCENTILE = 98.0
MAX_DEPTH_UNDER_POINTS = 2.0
#: A level with more than this share of the observed points under the cameras also under it (by
#: more than UNDER_MARGIN of the cameras' height over it) is no floor: nothing lies under a floor but
#: its reflections (measured: 2 % under openmvg_flat's glossy floor, 0-0.3 % under simulated ones;
#: 7-93 % under the tops of beds, counters and furniture against the walls).
MAX_SHARE_UNDER_FLOOR = 0.04
UNDER_MARGIN = 0.03
#: The level's relative uncertainty is at least this: where a boundary's edge lies within the
#: smoothing is a bias no averaging removes (openmvg_flat's level moves 0.8 % between a smoothing of
#: one pixel at 512 rows and EDGE_SIGMA_DEG).
MIN_RELATIVE_SD = 0.005
#: Fewer observations or panoramas than this: no search.
MIN_OBSERVATIONS = 100
MIN_VIEWS = 2


@dataclass
class BoundaryFloor:
    """The floor level the boundary search found, in the upright SfM frame."""

    level: float  # y of the floor (y down)
    #: standard uncertainty of `level` (SfM units): the spread of the panoramas' own best levels
    level_sd: float
    observations: int  # point observations that voted
    views: int  # panoramas that voted
    #: the peak's height over the background in robust standard deviations of the background
    contrast: float


def edge_image(pano: Panorama) -> tuple[np.ndarray, np.ndarray]:
    """[H,W] float32 vertical-gradient magnitude of a panorama (Gaussian-smoothed, averaged over
    COLUMN_WINDOW_DEG of longitude, periodic across the seam), zero where the mask is, and [H,W]
    float32 the share of valid pixels in the same window."""
    gray = cv2.cvtColor(pano.rgb, cv2.COLOR_RGB2GRAY).astype(np.float32) / 255.0
    h, w = gray.shape
    gray = cv2.GaussianBlur(gray, (0, 0), max(1.0, EDGE_SIGMA_DEG / 180.0 * h))
    grad = np.abs(cv2.Sobel(gray, cv2.CV_32F, 0, 1, ksize=3))
    valid = np.ones((h, w), np.float32)
    if pano.valid is not None:
        keep = pano.valid.astype(np.uint8)
        keep = cv2.erode(keep, np.ones((2 * MASK_MARGIN_PX + 1,) * 2, np.uint8), borderType=cv2.BORDER_REPLICATE)
        valid = keep.astype(np.float32)
    grad *= valid
    half = max(1, round(COLUMN_WINDOW_DEG / 360.0 * w / 2))
    out = []
    for img in (grad, valid):
        padded = np.concatenate([img[:, -half:], img, img[:, :half]], axis=1)
        out.append(cv2.blur(padded, (2 * half + 1, 1), borderType=cv2.BORDER_REPLICATE)[:, half:half + w])
    return out[0], out[1]


@dataclass
class _ViewVotes:
    """The observations of one panorama: where their feet land for a level."""

    image: np.ndarray  # [H,W,2] edge strength, valid share (edge_image)
    a: np.ndarray  # [M,3] camera-frame vector to the point
    b: np.ndarray  # [3] camera-frame down axis (world +y)
    point_y: np.ndarray  # [M] the points' world y

    def score(self, levels: np.ndarray, subset: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """[L] sums of edge strength and of valid share over the feet (of the observations
        `subset`, default all), for each level."""
        a, y = (self.a, self.point_y) if subset is None else (self.a[subset], self.point_y[subset])
        h, w = self.image.shape[:2]
        drop = (levels[:, None] - y[None, :]).astype(np.float32)  # [L,M]
        d = a.astype(np.float32)[None] + drop[..., None] * self.b.astype(np.float32)  # [L,M,3]
        lon = np.arctan2(d[..., 0], d[..., 2])
        lat = np.arctan2(-d[..., 1], np.hypot(d[..., 0], d[..., 2]))
        col = (lon * np.float32(0.5 / np.pi) + np.float32(0.5)) * w - np.float32(0.5)
        row = (np.float32(0.5) - lat * np.float32(1 / np.pi)) * h - np.float32(0.5)
        samples = remap_equirect(self.image, col, row)  # [L,M,2]
        # a point lies on or above the floor, never under it; and a foot next to its point lands on
        # the point's own texture (it is a feature), not on a boundary
        along = np.sum(d * a[None], axis=-1) / np.maximum(
            np.linalg.norm(d, axis=-1) * np.linalg.norm(a, axis=-1)[None], 1e-12)
        samples *= ((drop >= 0) & (along < np.float32(np.cos(np.radians(MIN_FOOT_SEPARATION_DEG)))))[..., None]
        total = samples.sum(axis=1, dtype=np.float64)
        return total[:, 0], total[:, 1]


def find_floor_level(panoramas: Sequence[Panorama], cam_to_world: Mapping[str, np.ndarray], points: np.ndarray,
                     seen_by: Mapping[str, np.ndarray] | None = None) -> BoundaryFloor | None:
    """The floor level (y, upright SfM frame) at which the feet of the sparse `points` land on
    image edges in the panoramas that observe them; None when no level stands out. `cam_to_world`:
    the placed panoramas' camera-to-world poses in the upright frame (y down); `seen_by`: view ->
    indices of the points it observes (missing or empty: every point)."""
    names = [p.name for p in panoramas if p.name in cam_to_world]
    if len(names) < MIN_VIEWS or len(points) == 0:
        return None
    by_name = {p.name: p for p in panoramas}
    points = np.asarray(points, float)
    votes: list[_ViewVotes] = []
    distances = []
    for name in names:
        pose = np.asarray(cam_to_world[name], float)
        rot, centre = pose[:3, :3], pose[:3, 3]
        idx = seen_by.get(name) if seen_by else None
        sel = points if idx is None or len(idx) == 0 else points[np.asarray(idx, int)]
        rel = sel - centre
        horizontal = np.hypot(rel[:, 0], rel[:, 2])
        elevation = np.degrees(np.arctan2(-rel[:, 1], horizontal))
        keep = (np.abs(elevation) < MAX_ELEVATION_DEG) & (horizontal > 0)
        if not keep.any():
            continue
        votes.append(_ViewVotes(np.stack(edge_image(by_name[name]), axis=-1), rel[keep] @ rot, rot[1, :].copy(),
                                sel[keep, 1]))
        distances.append(horizontal[keep])
    observations = sum(len(v.point_y) for v in votes)
    if len(votes) < MIN_VIEWS or observations < MIN_OBSERVATIONS:
        return None
    ref = max(float(np.asarray(cam_to_world[n])[1, 3]) for n in names)  # the lowest camera
    typical = float(np.median(np.concatenate(distances)))
    lo, hi = (typical * f for f in HEIGHT_RANGE)
    # walls reach down to the floor, and so do their lowest points, nearly: the floor is not
    # searched far below them
    lowest = float(np.percentile(np.concatenate([v.point_y for v in votes]), LOWEST_POINTS_PERCENTILE)) - ref
    if lowest > 0:
        hi = min(hi, MAX_DEPTH_UNDER_POINTS * lowest)
    if hi <= lo * np.exp(3 * COARSE_STEP):
        return None

    rng = np.random.default_rng(0)
    share = min(1.0, COARSE_OBSERVATIONS / observations)

    def sums(heights: np.ndarray, coarse: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """[views, L] sums of edge strength and of valid share under the feet, for each camera
        height of the lowest camera; the coarse search reads a random share of the observations."""
        e_out, w_out = np.zeros((len(votes), len(heights))), np.zeros((len(votes), len(heights)))
        for k, v in enumerate(votes):
            m = len(v.point_y)
            subset = np.sort(rng.choice(m, max(1, round(share * m)), replace=False)) if coarse else None
            chunk = max(1, 2_000_000 // (m if subset is None else len(subset)))
            for s in range(0, len(heights), chunk):
                e_out[k, s:s + chunk], w_out[k, s:s + chunk] = v.score(ref + heights[s:s + chunk], subset)
        return e_out, w_out

    coarse = np.exp(np.arange(np.log(lo), np.log(hi), COARSE_STEP))
    e, w = (x.sum(axis=0) for x in sums(coarse, coarse=True))
    mean = e / np.maximum(w, 1e-6)
    background = median_filter(mean, size=max(3, round(BACKGROUND_SPAN / COARSE_STEP) | 1), mode="nearest")
    # the excess edge strength under the feet, in units of its noise: a mean over few feet is noisy
    excess = (mean - background) * np.sqrt(w)
    noise = 1.4826 * float(np.median(np.abs(excess - np.median(excess))))
    contrast = excess / max(noise, 1e-12)
    # horizontal lines at one height run along many walls too (the tops of counters, sills, a bed or
    # a sofa against the wall), but points lie under them: nothing lies under a floor
    depth = np.sort(np.concatenate([v.point_y for v in votes])) - ref
    depth = depth[depth > 0]  # the observed points under the lowest camera
    under = (len(depth) - np.searchsorted(depth, coarse * (1.0 + UNDER_MARGIN))) / max(len(depth), 1)
    peaks = [k for k in range(1, len(contrast) - 1)
             if contrast[k] >= MIN_CONTRAST and contrast[k] >= contrast[k - 1] and contrast[k] >= contrast[k + 1]
             and under[k] <= MAX_SHARE_UNDER_FLOOR]
    if not peaks:
        return None
    peak = max(peaks, key=lambda k: contrast[k])
    # fine: +-2 coarse steps at FINE_STEP, every observation, the background from the coarse grid
    fine = coarse[peak] * np.exp(np.arange(-2 * COARSE_STEP, 2 * COARSE_STEP + FINE_STEP / 2, FINE_STEP))
    fine_e, fine_w = sums(fine)
    fine_mean = fine_e.sum(axis=0) / np.maximum(fine_w.sum(axis=0), 1e-6)
    best = int(np.argmax(fine_mean - np.interp(np.log(fine), np.log(coarse), background)))
    height = float(fine[best])
    if 0 < best < len(fine) - 1:  # parabola through the peak and its neighbours (log grid)
        y0, y1, y2 = fine_mean[best - 1:best + 2]
        den = y0 - 2 * y1 + y2
        if den < 0:
            height *= float(np.exp(0.5 * (y0 - y2) / den * FINE_STEP))
    # uncertainty: the spread of the panoramas' own best heights near the peak, over sqrt(views)
    own = fine[np.argmax(fine_e / np.maximum(fine_w, 1e-6), axis=1)]
    log_own = np.log(own / height)
    mad = 1.4826 * float(np.median(np.abs(log_own - np.median(log_own))))
    level_sd = height * max(mad / np.sqrt(len(votes)), MIN_RELATIVE_SD)
    return BoundaryFloor(ref + height, float(level_sd), observations, len(votes), float(contrast[peak]))


def floor_cue(panoramas: Sequence[Panorama], seen_by: Mapping[str, np.ndarray] | None = None) -> FloorCue:
    """find_floor_level as a cue of sfm.frame.align_to_floor: a level Floor at the level found,
    its offset's uncertainty the search's."""

    def cue(cam_to_world: dict[str, np.ndarray], points: np.ndarray) -> Floor | None:
        found = find_floor_level(panoramas, cam_to_world, points, seen_by)
        if found is None:
            return None
        return Floor(np.array([0.0, 1.0, 0.0]), -found.level, found.observations, 0.0, offset_sd=found.level_sd)

    return cue
