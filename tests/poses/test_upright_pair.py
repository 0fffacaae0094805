"""The upright two-view solver (sfm.upright_pair) on synthetic bearings."""

from __future__ import annotations

import numpy as np

from sfm.upright_pair import PairPose, epipolar_error, search_pose, triangulate


def _unit(x: np.ndarray) -> np.ndarray:
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


def test_pose_found_among_90_percent_wrong_matches():
    rng = np.random.default_rng(0)
    truth = PairPose(theta=np.radians(37.3), phi=np.radians(-121.4), score=0.0, runner_up=0.0)
    a_from_b = truth.a_from_b
    # 30 points of a room around both cameras (baseline 1), seen with 0.05° of noise
    points = rng.uniform([-4, -1.5, -4], [4, 1.0, 4], (30, 3))
    b1 = _unit(points + rng.normal(0, 1e-3, points.shape) * np.linalg.norm(points, axis=1, keepdims=True))
    in_b = (points - a_from_b[:3, 3]) @ a_from_b[:3, :3]  # the points in b's frame
    b2 = _unit(in_b + rng.normal(0, 1e-3, in_b.shape) * np.linalg.norm(in_b, axis=1, keepdims=True))
    # 270 wrong matches: unrelated directions
    b1 = np.concatenate([b1, _unit(rng.normal(size=(270, 3)))])
    b2 = np.concatenate([b2, _unit(rng.normal(size=(270, 3)))])
    order = rng.permutation(len(b1))
    b1, b2 = b1[order], b2[order]

    coarse = search_pose(b1, b2, step_deg=1.0, tau_deg=1.0)
    assert coarse.score > 1.2 * coarse.runner_up
    fine = search_pose(b1, b2, step_deg=0.05, tau_deg=0.3, around=coarse, span_deg=2.0)
    assert abs(np.degrees(fine.theta - truth.theta)) < 0.1
    assert abs(np.degrees(fine.phi - truth.phi)) < 0.2

    # the inliers are the true matches and triangulate onto the points (baseline 1)
    w2 = b2 @ fine.a_from_b[:3, :3].T
    error, front = epipolar_error(b1, w2, fine.baseline)
    inliers = front & (error < np.radians(0.3))
    assert inliers[np.argsort(order)[:30]].sum() >= 28 and inliers.sum() <= 32
    tri = triangulate(b1[inliers], w2[inliers], fine.baseline)
    matched = order[inliers]
    good = matched < 30
    assert np.median(np.linalg.norm(tri[good] - points[matched[good]], axis=1)) < 0.05


def test_epipolar_error_is_the_angle_to_the_plane_and_cheirality():
    c = np.array([0.0, 0.0, 1.0])
    b1 = _unit(np.array([1.0, 0.0, 1.0]))  # a point at (1, 0, 1) seen from the origin ...
    w2 = np.array([1.0, 0.0, 0.0])  # ... and from (0, 0, 1)
    error, front = epipolar_error(b1, w2, c)
    assert error < 1e-9 and front
    _, front = epipolar_error(b1, -w2, c)  # rays diverge: behind the second camera
    assert not front
    tilted = _unit(np.array([1.0, np.tan(np.radians(2.0)), 0.0]))
    error, _ = epipolar_error(b1, tilted, c)
    assert abs(np.degrees(error) - 2.0) < 1e-6


def test_features_skip_views_without_any_and_keep_the_rest():
    """A panorama textured only around one direction: most of the rig's perspective views find no
    feature (OpenCV 5 returns an empty descriptor array there, 4 returned None), and every bearing
    found lies in the textured part."""
    from sfm.records import Panorama
    from sfm.upright_pair import UprightPairOptions, features

    h, w = 128, 256
    rng = np.random.default_rng(0)
    rgb = np.full((h, w, 3), 128, np.uint8)
    cols = slice(w // 2 - 24, w // 2 + 24)  # ±34° of longitude around the image centre (+z)
    rows = slice(h // 2 - 24, h // 2 + 24)
    blocks = rng.integers(0, 256, (6, 6, 3), dtype=np.uint8)
    rgb[rows, cols] = np.kron(blocks, np.ones((8, 8, 1), np.uint8))
    dirs, descs = features(Panorama("textured_front", rgb), UprightPairOptions())
    assert len(dirs) == len(descs) > 0
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=1), 1.0, rtol=1e-6)
    assert (dirs[:, 2] > 0.5).all()  # within ~60° of +z, where the texture is
