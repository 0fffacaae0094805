"""Relative pose of two levelled panoramas at one camera height (the upright prior).

360° cameras are levelled, and a capture's panoramas are usually taken from one
tripod height, so the pose of panorama b relative to panorama a has two degrees
of freedom: the yaw ``theta`` of b's frame about gravity (+y) and the azimuth
``phi`` of b's centre seen from a (the baseline is horizontal; its length is
fixed later by the floor, sfm.frame). COLMAP's five-point RANSAC needs far more
correct matches than two panoramas metres apart give (docs/poses.md): with
two unknowns an exhaustive search over a grid of (theta, phi) with a truncated
angular epipolar error finds the pose among 95 % wrong matches.

Steps: SIFT on the perspective views of sfm.rig (bearings in the panorama
frame, DESIGN.md axes), RootSIFT with a lax ratio test, at most one match per
small cell of either sphere (a chandelier's hundred features are one
observation, not a hundred); a coarse search over all (theta, phi); guided
matching in a band around the winner's epipolar planes (the ratio test among
the few candidates near the plane passes many correct matches that the global
ratio test lost); a fine search over those; the inliers triangulated.

The coarse search is fast (search_pose_peaks: a 3x coarser grid, its best peaks
refined); where its pose is not convincing (not distinct, too few guided
matches or inliers) the exhaustive search (search_pose) runs on the same
matches and its pose is verified instead (issue 36: speed must not cost real
pairs). PairResult.search and SearchLog say which ran.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field

import cv2
import numpy as np

from panogeom.equirect import angles_to_pixel, dirs_to_angles
from sfm.records import Panorama, Reconstruction
from sfm.rig import VirtualRig, rotation_about_y


@dataclass
class UprightPairOptions:
    #: SIFT contrast threshold (OpenCV's default 0.04 leaves too few features on indoor walls)
    contrast_threshold: float = 0.02
    #: the strongest features kept per panorama: the pair's distance matrices grow with the square
    max_features: int = 5000
    #: ratio test of the putative matches: lax, the search is robust
    ratio: float = 0.95
    #: at most one putative match per cell of this size (degrees) in either panorama
    cell_deg: float = 2.0
    coarse_step_deg: float = 1.0
    coarse_tau_deg: float = 1.0
    #: the coarse search scores at most this many putative matches (the closest in descriptor space)
    coarse_max_matches: int = 800
    #: the coarse search refines this many peaks of a 3x coarser grid (search_pose_peaks); 0: every pose
    coarse_peaks: int = 12
    #: where the peak search's pose is not convincing (not distinct, too few guided matches or
    #: inliers), search every pose (search_pose) on the same matches and verify its pose instead
    exhaustive_fallback: bool = True
    #: inliers the exhaustive fallback's pose needs (min_inliers for the others): searching every
    #: pose of a pair the fast search found nothing in finds a distinct wrong one more often (on 110
    #: simulated pairs: 3 right ones with 42-60 inliers, 1 wrong one with 23; docs/poses.md)
    fallback_min_inliers: int = 30
    #: guided matching: candidates within this angle of the epipolar plane, ratio test among them
    guided_band_deg: float = 3.0
    guided_ratio: float = 0.8
    #: RootSIFT distance a guided match may have at most (2 is the largest possible)
    guided_max_distance: float = 0.7
    fine_span_deg: float = 2.5
    fine_step_deg: float = 0.05
    fine_tau_deg: float = 0.3
    #: the coarse pose must score this many times the best pose at least 5° from it, and keep this
    #: many inliers; unrelated panoramas can pass both (docs/poses.md): the caller vouches for overlap
    min_distinct: float = 1.15
    min_inliers: int = 20
    #: where given, every pair searched is counted in it (which search ran; SearchLog)
    log: SearchLog | None = field(default=None, repr=False, compare=False)


#: Something that travels with the camera (a tripod, a hand, a holder) sits at one bearing in
#: every panorama: putative matches whose bearings agree within this angle in the two panoramas'
#: own frames, this far below the horizon, are taken for it. A static point does that only on one
#: curve (equidistant from both centres, where the yaw between the panoramas undoes the parallax):
#: 50° or more below the horizon that curve holds hardly any point, while tripods and holders lie
#: 55-80° down (zind_pair's 65-77°, openmvg_flat's 65-75°). At 40-55° a hand-held walk-through
#: gave 10 such static points between views 0.4 m apart (openmvg_flat at 1024 rows; docs/poses.md).
CAMERA_FIXED_DEG = 1.0
CAMERA_FIXED_BELOW_DEG = 50.0
#: ... and this many of them in one pair say that it is there.
CAMERA_FIXED_MIN = 8


@dataclass
class SearchLog:
    """Which searches a solve ran, summed over its pairs (sfm.upright_global searches pairs in
    threads: counts are taken under a lock)."""

    #: pairs searched (the coarse search ran)
    pairs: int = 0
    #: the fast peak search ran first (False: coarse_peaks=0, the exhaustive search only)
    fast: bool = True
    #: pairs the exhaustive search ran on after the fast one found nothing convincing
    exhaustive: int = 0
    #: of those, pairs whose exhaustive pose was verified
    recovered: int = 0
    #: seconds spent in the exhaustive fallback (search and verification)
    exhaustive_seconds: float = 0.0
    #: the most putative matches of one pair at one bearing in both panoramas, well below the
    #: horizon (camera_fixed_matches): something travelling with the camera, unmasked
    camera_fixed: int = 0
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False, compare=False)

    def add(self, *, fast: bool, exhaustive: bool = False, recovered: bool = False, seconds: float = 0.0,
            camera_fixed: int = 0) -> None:
        with self._lock:
            self.pairs += 1
            self.fast = self.fast and fast
            self.exhaustive += exhaustive
            self.recovered += recovered
            self.exhaustive_seconds += seconds
            self.camera_fixed = max(self.camera_fixed, camera_fixed)

    def describe(self) -> str:
        """One phrase: which search ran on how many pairs."""
        if not self.fast:
            return f"exhaustive search on {self.pairs} pair{'s' * (self.pairs != 1)}"
        text = f"fast search on {self.pairs} pair{'s' * (self.pairs != 1)}"
        if self.exhaustive:
            text += (f"; exhaustive search on {self.exhaustive} where it found nothing convincing "
                     f"({self.recovered} verified, {self.exhaustive_seconds:.1f} s)")
        return text


@dataclass
class PairPose:
    """Panorama b relative to panorama a: b's frame is a's turned by `theta` about +y, its centre
    lies along (sin phi, 0, cos phi) from a's (angles in radians)."""

    theta: float
    phi: float
    #: the search's score (truncated inlier count) and the best score at least 5° away
    score: float
    runner_up: float

    @property
    def a_from_b(self) -> np.ndarray:
        """4x4 taking b's camera frame to a's, baseline of length 1."""
        out = np.eye(4)
        out[:3, :3] = rotation_about_y(np.degrees(self.theta))
        out[:3, 3] = self.baseline
        return out

    @property
    def baseline(self) -> np.ndarray:
        return np.array([np.sin(self.phi), 0.0, np.cos(self.phi)])


@dataclass
class PairResult:
    pose: PairPose
    putative: int  # matches after the ratio test and one per cell
    guided: int  # matches of the guided matching
    inliers: int  # guided matches within fine_tau_deg of the fine pose
    residual_deg: np.ndarray  # [inliers] angular epipolar error
    reconstruction: Reconstruction
    #: [inliers,2] feature indices (into `features` of a and of b) of the inlier matches
    matches: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), int))
    #: the search whose pose this is: "peaks" (the fast search), "exhaustive" (coarse_peaks=0) or
    #: "exhaustive fallback" (the fast search's pose was not convincing)
    search: str = "peaks"


def epipolar_error(b1: np.ndarray, w2: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For unit bearings b1 (camera a) and w2 (camera b, rotated into a's frame) and the unit
    baseline c (broadcasting over leading axes): the larger of the two angles between a bearing
    and the other's epipolar plane (radians), and whether the rays meet in front of both cameras."""
    num = np.abs(np.sum(np.cross(b1, w2) * c, axis=-1))
    ac, bc, ab = np.sum(b1 * c, axis=-1), np.sum(w2 * c, axis=-1), np.sum(b1 * w2, axis=-1)
    sin_a = np.sqrt(np.maximum(1.0 - bc**2, 1e-12))  # |w2 x c|
    sin_b = np.sqrt(np.maximum(1.0 - ac**2, 1e-12))  # |b1 x c|
    error = np.arcsin(np.clip(np.maximum(num / sin_a, num / sin_b), 0.0, 1.0))
    # b1 l1 = c + w2 l2 in least squares: both depths positive
    return error, (ac - ab * bc > 0) & (ab * ac - bc > 0)


def _baselines(phis: np.ndarray) -> np.ndarray:
    return np.stack([np.sin(phis), np.zeros_like(phis), np.cos(phis)], axis=-1)


def score_grid(b1: np.ndarray, b2: np.ndarray, thetas: np.ndarray, phis: np.ndarray, tau: float,
               chunk: int = 256) -> np.ndarray:
    """[T,P] truncated quadratic score sum(1 - min(e / tau, 1)^2) of the correspondences b1[i] <->
    b2[i] for every (theta, phi); a match whose rays meet behind a camera scores 0. The error is
    taken as its sine (within 1e-4 of the angle at the tolerances used, a degree or less): no
    arcsin over the whole grid, in float32, which makes the exhaustive search several times faster.
    The correspondences are taken `chunk` at a time, every theta over each chunk: the [chunk,P]
    intermediates then stay in the CPU's cache (800 matches at once over 360 phis did not: the
    exhaustive search took 8x as long)."""
    b1 = np.asarray(b1, np.float32)
    b2 = np.asarray(b2, np.float32)
    c = np.ascontiguousarray(_baselines(phis).astype(np.float32).T)  # [3,P]
    inv_sin_tau = np.float32(1.0 / np.sin(tau))
    rotations = [rotation_about_y(np.degrees(theta)).T.astype(np.float32) for theta in thetas]
    out = np.zeros((len(thetas), len(phis)))
    for start in range(0, len(b1), chunk):
        a1, a2 = b1[start:start + chunk], b2[start:start + chunk]
        ac = a1 @ c  # [n,P]
        sin_b = np.sqrt(np.maximum(1.0 - ac**2, 1e-12))
        for i, rotation in enumerate(rotations):
            w2 = a2 @ rotation
            num = np.abs(np.cross(a1, w2) @ c)
            bc = w2 @ c
            ab = np.sum(a1 * w2, axis=1)[:, None]
            # the larger of the two plane angles: num over the smaller of the two sines
            ratio = np.minimum(num / np.minimum(np.sqrt(np.maximum(1.0 - bc**2, 1e-12)), sin_b) * inv_sin_tau, 1.0)
            front = (ac - ab * bc > 0) & (ab * ac - bc > 0)
            out[i] += np.sum(np.where(front, 1.0 - ratio**2, 0.0), axis=0, dtype=np.float64)
    return out


def _wrapped_distance(n: int, k: int) -> np.ndarray:
    d = np.abs(np.arange(n) - k)
    return np.minimum(d, n - d)


def search_pose(b1: np.ndarray, b2: np.ndarray, step_deg: float = 1.0, tau_deg: float = 1.0,
                around: PairPose | None = None, span_deg: float = 180.0) -> PairPose:
    """The (theta, phi) of the grid (step `step_deg`, over every angle or within `span_deg` of
    `around`) with the best truncated score of the correspondences b1 <-> b2."""
    offsets = np.radians(np.arange(-span_deg, span_deg, step_deg))
    if around is None:
        thetas = phis = np.radians(np.arange(0.0, 360.0, step_deg))
    else:
        thetas, phis = around.theta + offsets, around.phi + offsets
    scores = score_grid(b1, b2, thetas, phis, np.radians(tau_deg))
    i, j = np.unravel_index(np.argmax(scores), scores.shape)
    runner_up = 0.0
    if around is None:
        radius = int(np.ceil(5.0 / step_deg))
        near_theta = _wrapped_distance(len(thetas), i) <= radius
        far = ~(near_theta[:, None] & (_wrapped_distance(len(phis), j) <= radius)[None])
        runner_up = float(scores[far].max())
    theta = float(np.mod(thetas[i] + np.pi, 2 * np.pi) - np.pi)
    phi = float(np.mod(phis[j] + np.pi, 2 * np.pi) - np.pi)
    return PairPose(theta, phi, float(scores[i, j]), runner_up)


def search_pose_peaks(b1: np.ndarray, b2: np.ndarray, step_deg: float = 1.0, tau_deg: float = 1.0,
                      peaks: int = 12, factor: int = 3) -> PairPose:
    """search_pose over every angle, about `factor`^2 times faster: the score on a grid `factor`
    times coarser (tolerance likewise) finds the `peaks` best local maxima; the full-resolution
    grid is evaluated only around them (±`factor`+1 steps). The best and the runner-up (best at
    least 5° away) are those of the evaluated points: the same as the exhaustive search's when
    the runner-up's peak is among the coarse grid's `peaks` best."""
    coarse_step = step_deg * factor
    grid = np.radians(np.arange(0.0, 360.0, coarse_step))
    coarse = score_grid(b1, b2, grid, grid, np.radians(tau_deg * factor))
    # local maxima of the wrapped coarse grid
    neighbours = np.max([np.roll(coarse, (di, dj), axis=(0, 1)) for di in (-1, 0, 1) for dj in (-1, 0, 1)
                         if di or dj], axis=0)
    candidates = np.argwhere(coarse >= neighbours)
    order = np.argsort(-coarse[candidates[:, 0], candidates[:, 1]], kind="stable")[:peaks]
    span = np.arange(-(factor + 1), factor + 2) * step_deg
    thetas, phis, scores = [], [], []
    for i, j in candidates[order]:
        t = np.radians(i * coarse_step + span)
        f = np.radians(j * coarse_step + span)
        sc = score_grid(b1, b2, t, f, np.radians(tau_deg))
        thetas.append(np.repeat(t, len(f)))
        phis.append(np.tile(f, len(t)))
        scores.append(sc.ravel())
    thetas, phis, scores = np.concatenate(thetas), np.concatenate(phis), np.concatenate(scores)
    best = int(np.argmax(scores))

    def wrapped(a):
        return np.abs(np.mod(a + np.pi, 2 * np.pi) - np.pi)

    limit = np.radians(5.0 + 1e-6)  # within 5° is near, as in search_pose
    far = ~((wrapped(thetas - thetas[best]) <= limit) & (wrapped(phis - phis[best]) <= limit))
    runner_up = float(scores[far].max()) if far.any() else 0.0
    theta = float(np.mod(thetas[best] + np.pi, 2 * np.pi) - np.pi)
    phi = float(np.mod(phis[best] + np.pi, 2 * np.pi) - np.pi)
    return PairPose(theta, phi, float(scores[best]), runner_up)


def features(pano: Panorama, options: UprightPairOptions) -> tuple[np.ndarray, np.ndarray]:
    """Unit bearings [N,3] in the panorama frame and RootSIFT descriptors [N,128] of SIFT features
    found on the panorama's perspective views (sfm.rig), outside its invalid pixels, strongest
    (largest SIFT response) first: the first K are the panorama's K strongest."""
    rig = VirtualRig(pano.rgb.shape[0])
    sift = cv2.SIFT_create(contrastThreshold=options.contrast_threshold)
    dirs, descs, strength = [], [], []
    bgr = cv2.cvtColor(pano.rgb, cv2.COLOR_RGB2BGR)
    for (image, mask), pano_from_cam in zip(rig.render(bgr, pano.valid), rig.pano_from_cams):
        keypoints, desc = sift.detectAndCompute(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY), mask)
        if desc is None or not keypoints:  # OpenCV 4 gives None for a view without features, 5 an empty array
            continue
        # OpenCV puts pixel centres at integers, the rig's rays at +0.5 (sfm.rig)
        uv = (np.array([k.pt for k in keypoints]) + 0.5 - rig.size / 2.0) / rig.focal
        rays = np.column_stack([uv, np.ones(len(uv))]) @ pano_from_cam.T
        dirs.append(rays / np.linalg.norm(rays, axis=1, keepdims=True))
        desc = desc / (desc.sum(axis=1, keepdims=True) + 1e-9)
        descs.append(np.sqrt(desc).astype(np.float32))
        strength.append(np.array([k.response for k in keypoints]))
    if not dirs:
        return np.zeros((0, 3)), np.zeros((0, 128), np.float32)
    order = np.argsort(-np.concatenate(strength), kind="stable")[:options.max_features]
    return np.concatenate(dirs)[order], np.concatenate(descs)[order]


def descriptor_distance(d1: np.ndarray, d2: np.ndarray) -> np.ndarray:
    """[N1,N2] Euclidean distances of unit RootSIFT descriptors (float32)."""
    return np.sqrt(np.maximum(2.0 - 2.0 * (d1 @ d2.T), 0.0))


def _cells(bearings: np.ndarray, cell_deg: float) -> np.ndarray:
    lon = np.degrees(np.arctan2(bearings[:, 0], bearings[:, 2]))
    lat = np.degrees(np.arcsin(np.clip(-bearings[:, 1], -1.0, 1.0)))
    column = np.floor((lon + 180.0) / cell_deg).astype(np.int64)
    return column * 100000 + np.floor((lat + 90.0) / cell_deg).astype(np.int64)


def two_nearest(distance: np.ndarray) -> np.ndarray:
    """[N,min(2,M)] column indices of each row's smallest and second smallest entry (a partition,
    not a full sort: the rows hold thousands of candidates)."""
    if distance.shape[1] <= 2:
        return np.argsort(distance, axis=1)
    two = np.argpartition(distance, 1, axis=1)[:, :2]
    first = np.take_along_axis(distance, two[:, :1], axis=1)[:, 0]
    swap = np.take_along_axis(distance, two[:, 1:], axis=1)[:, 0] < first
    two[swap] = two[swap][:, ::-1]
    return two


def putative_matches(b1: np.ndarray, b2: np.ndarray, distance: np.ndarray, options: UprightPairOptions) -> np.ndarray:
    """[M,2] index pairs: nearest neighbours passing the ratio test, then the best (smallest
    distance) of those in each cell of either sphere."""
    if distance.shape[1] < 2:
        return np.zeros((0, 2), int)
    nearest = two_nearest(distance)
    d = np.take_along_axis(distance, nearest, axis=1)
    pairs = np.column_stack([np.arange(len(b1)), nearest[:, 0]])[d[:, 0] < options.ratio * d[:, 1]]
    pairs = pairs[np.argsort(distance[pairs[:, 0], pairs[:, 1]], kind="stable")]
    first = np.zeros(len(pairs), bool)
    first[np.unique(_cells(b1[pairs[:, 0]], options.cell_deg), return_index=True)[1]] = True
    second = np.zeros(len(pairs), bool)
    second[np.unique(_cells(b2[pairs[:, 1]], options.cell_deg), return_index=True)[1]] = True
    return pairs[first & second]


def guided_matches(b1: np.ndarray, b2: np.ndarray, distance: np.ndarray, pose: PairPose,
                   options: UprightPairOptions, chunk: int = 1024) -> np.ndarray:
    """[M,2] index pairs: for each feature of a, the nearest feature of b among those within
    guided_band_deg of its epipolar plane (in front of both cameras), if it passes a ratio test
    against the second nearest there and is close enough."""
    w2 = (b2 @ pose.a_from_b[:3, :3].T).astype(np.float32)
    c = pose.baseline.astype(np.float32)
    # epipolar_error for every pair at once, as matrix products: |b1.(w2 x c)| over the smaller of
    # |w2 x c| and |b1 x c| is the sine of the larger plane angle
    normals = np.cross(w2, c)
    sin_a = np.linalg.norm(normals, axis=1)
    bc = w2 @ c
    sin_band = np.float32(np.sin(np.radians(options.guided_band_deg)))
    out = []
    for start in range(0, len(b1), chunk):
        a = b1[start:start + chunk].astype(np.float32)
        ac = a @ c
        sin_b = np.sqrt(np.maximum(1.0 - ac**2, 1e-12))
        num = np.abs(a @ normals.T)
        ab = a @ w2.T
        near = num < sin_band * np.minimum(sin_a[None], sin_b[:, None])
        front = (ac[:, None] - ab * bc[None] > 0) & (ab * ac[:, None] - bc[None] > 0)
        d = np.where(near & front, distance[start:start + chunk], np.inf)
        nearest = two_nearest(d)
        v = np.take_along_axis(d, nearest, axis=1)
        if v.shape[1] < 2:
            v = np.column_stack([v, np.full(len(v), np.inf)])
        ok = np.isfinite(v[:, 0]) & (v[:, 0] < options.guided_ratio * v[:, 1]) & (v[:, 0] < options.guided_max_distance)
        out.extend((start + k, nearest[k, 0]) for k in np.flatnonzero(ok))
    return np.array(out, dtype=int).reshape(-1, 2)


def triangulate(b1: np.ndarray, w2: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Midpoints [N,3] of the closest points of the rays b1 (from the origin) and w2 (from c)."""
    ab, ac, bc = np.sum(b1 * w2, axis=1), b1 @ c, w2 @ c
    den = np.maximum(1.0 - ab**2, 1e-12)
    l1, l2 = (ac - ab * bc) / den, (ab * ac - bc) / den
    return 0.5 * (l1[:, None] * b1 + c + l2[:, None] * w2)


def relative_pose(a: Panorama, b: Panorama, options: UprightPairOptions | None = None) -> PairResult | None:
    """The upright relative pose of panorama b to a and the triangulated inliers as a
    Reconstruction in a's frame (baseline 1); None when too few matches are left to search, the
    best pose is not clearly better than every other, or too few inliers remain."""
    options = options or UprightPairOptions()
    f1, d1 = features(a, options)
    f2, d2 = features(b, options)
    return pose_from_features(a, b, (f1, d1), (f2, d2), options)


def pose_from_features(a: Panorama, b: Panorama, feat_a: tuple[np.ndarray, np.ndarray],
                       feat_b: tuple[np.ndarray, np.ndarray], options: UprightPairOptions) -> PairResult | None:
    """relative_pose on features already extracted (`features`): the N-view solver extracts each
    panorama's once."""
    (f1, d1), (f2, d2) = feat_a, feat_b
    if len(f1) < 2 or len(f2) < 2:
        return None
    distance = descriptor_distance(d1, d2)
    pairs = putative_matches(f1, f2, distance, options)
    if len(pairs) < 8:
        return None
    # the putative matches are sorted by descriptor distance: the search takes the best ones
    top = pairs[:options.coarse_max_matches]
    b1, b2 = f1[top[:, 0]], f2[top[:, 1]]
    fixed = camera_fixed_matches(b1, b2)
    if not options.coarse_peaks:
        coarse = search_pose(b1, b2, options.coarse_step_deg, options.coarse_tau_deg)
        result = _verified(a, b, f1, f2, distance, coarse, len(pairs), options, "exhaustive", options.min_inliers)
        if options.log is not None:
            options.log.add(fast=False, camera_fixed=fixed)
        return result
    coarse = search_pose_peaks(b1, b2, options.coarse_step_deg, options.coarse_tau_deg, options.coarse_peaks)
    result = _verified(a, b, f1, f2, distance, coarse, len(pairs), options, "peaks", options.min_inliers)
    if result is not None or not options.exhaustive_fallback:
        if options.log is not None:
            options.log.add(fast=True, camera_fixed=fixed)
        return result
    # nothing convincing: the fast search may have missed the peak (it refines only the coarse
    # grid's best peaks, and the coarse grid's wider tolerance lets the wrong matches bury a
    # narrow one); the exhaustive search cannot miss it
    t0 = time.perf_counter()
    full = search_pose(b1, b2, options.coarse_step_deg, options.coarse_tau_deg)
    # the same best pose: its runner-up is no smaller and every later step the same, so no better
    same = np.isclose(full.theta, coarse.theta) and np.isclose(full.phi, coarse.phi)
    if not same:
        result = _verified(a, b, f1, f2, distance, full, len(pairs), options, "exhaustive fallback",
                           options.fallback_min_inliers)
    if options.log is not None:
        options.log.add(fast=True, exhaustive=True, recovered=result is not None,
                        seconds=time.perf_counter() - t0, camera_fixed=fixed)
    return result


def camera_fixed_matches(b1: np.ndarray, b2: np.ndarray) -> int:
    """How many of the correspondences b1[i] <-> b2[i] sit at one bearing in both panoramas' own
    frames (within CAMERA_FIXED_DEG), more than CAMERA_FIXED_BELOW_DEG below the horizon: features
    of something travelling with the camera (a tripod, a hand), which no nadir mask removed."""
    if not len(b1):
        return 0
    below = np.sin(np.radians(CAMERA_FIXED_BELOW_DEG))
    same = np.sum(b1 * b2, axis=1) > np.cos(np.radians(CAMERA_FIXED_DEG))
    return int(np.sum(same & (b1[:, 1] > below) & (b2[:, 1] > below)))  # y is down


def _verified(a: Panorama, b: Panorama, f1: np.ndarray, f2: np.ndarray, distance: np.ndarray, coarse: PairPose,
              putative: int, options: UprightPairOptions, search: str, min_inliers: int) -> PairResult | None:
    """The coarse pose verified and refined: distinct, guided matches, a fine search over them,
    `min_inliers` inliers; None where it fails a step."""
    if coarse.score < options.min_distinct * coarse.runner_up:
        return None
    guided = guided_matches(f1, f2, distance, coarse, options)
    if len(guided) < 8:
        return None
    g1, g2 = f1[guided[:, 0]], f2[guided[:, 1]]
    fine = search_pose(g1, g2, options.fine_step_deg, options.fine_tau_deg, around=coarse,
                       span_deg=options.fine_span_deg)
    pose = PairPose(fine.theta, fine.phi, coarse.score, coarse.runner_up)
    w2 = g2 @ pose.a_from_b[:3, :3].T
    error, front = epipolar_error(g1, w2, pose.baseline)
    inliers = front & (error < np.radians(options.fine_tau_deg))
    if inliers.sum() < min_inliers:
        return None
    points = triangulate(g1[inliers], w2[inliers], pose.baseline)
    colors = np.array([bearing_color(a, x) for x in g1[inliers]], dtype=np.uint8).reshape(-1, 3)
    residual = np.degrees(error[inliers])
    # equirect pixels per radian, to report the angular error where COLMAP reports pixels
    px = a.rgb.shape[1] / (2.0 * np.pi) * np.radians(float(residual.mean()) if len(residual) else 0.0)
    recon = Reconstruction(
        cam_from_world={a.name: np.eye(4), b.name: np.linalg.inv(pose.a_from_b)},
        reprojection_error={a.name: px, b.name: px},
        observations={a.name: int(inliers.sum()), b.name: int(inliers.sum())},
        points=points, colors=colors, track_length=np.full(len(points), 2), verified_pairs=1)
    return PairResult(pose, putative, len(guided), int(inliers.sum()), residual, recon, guided[inliers], search)


def bearing_color(pano: Panorama, bearing: np.ndarray) -> np.ndarray:
    h, w = pano.rgb.shape[:2]
    col, row = angles_to_pixel(*dirs_to_angles(bearing), h, w)
    return pano.rgb[int(np.clip(round(float(row)), 0, h - 1)), int(round(float(col))) % w]
