"""The upright N-view solver's global steps (sfm.upright_global) on synthetic geometry: yaw
averaging with a wrong pair, positions of a collinear chain from length ratios, tracks, and the
joint refinement."""

from __future__ import annotations

import numpy as np

from sfm.rig import rotation_about_y
from sfm.upright_global import (PairEdge, Tracks, angular_errors, average_yaws, build_tracks, components,
                                direction_error, fit_positions, length_ratios, refine, triangulate_tracks)
from sfm.upright_pair import PairPose, PairResult


def _wrap(x):
    return (np.asarray(x) + np.pi) % (2 * np.pi) - np.pi


def test_yaw_averaging_rejects_the_inconsistent_pair():
    rng = np.random.default_rng(0)
    yaw = rng.uniform(-np.pi, np.pi, 6)
    edges = [(i, j, float(_wrap(yaw[j] - yaw[i] + rng.normal(0, 0.002))), 50.0)
             for i in range(6) for j in range(i + 1, 6) if j - i <= 2]
    edges.append((0, 3, float(_wrap(yaw[3] - yaw[0] + 0.5)), 400.0))  # wrong, and the strongest pair
    estimate, agree = average_yaws(6, edges, np.radians(2.0))
    assert not agree[-1] and agree[:-1].all()
    relative = _wrap(estimate - estimate[0] - (yaw - yaw[0]))
    assert np.degrees(np.abs(relative)).max() < 0.3


def _edge(i, j, centres, yaws, matches=None):
    """A pair result as the pair solver would give it: j's yaw and direction relative to i."""
    d = centres[j] - centres[i]
    local = rotation_about_y(np.degrees(-yaws[i])) @ d
    pose = PairPose(float(_wrap(yaws[j] - yaws[i])), float(np.arctan2(local[0], local[2])), 0.0, 0.0)
    m = np.zeros((0, 2), int) if matches is None else matches
    return PairEdge(i, j, PairResult(pose, 0, 0, max(len(m), 30), np.zeros(0), None, m))


def _scene(rng, centres, yaws, n_points=400):
    """Points around the cameras, their bearings per camera, and every pair's matches (feature k of
    every view is point k when visible)."""
    points = rng.uniform([-8, -2.5, -3], [8, 0.0, 3], (n_points, 3))
    feats = []
    for c, y in zip(centres, yaws):
        local = (points - c) @ rotation_about_y(np.degrees(y))  # R^T (p - c)
        feats.append((local / np.linalg.norm(local, axis=1, keepdims=True), None))
    return points, feats


def test_collinear_chain_gets_its_lengths_from_the_shared_points():
    # four cameras on a line, spacings 1, 3, 2: directions alone say nothing about lengths
    rng = np.random.default_rng(1)
    centres = np.array([[0.0, 0, 0], [1.0, 0, 0], [4.0, 0, 0], [6.0, 0, 0]])
    yaws = rng.uniform(-np.pi, np.pi, 4)
    points, feats = _scene(rng, centres, yaws)
    near = [np.flatnonzero(np.linalg.norm(points[:, [0, 2]] - centres[k, [0, 2]], axis=1) < 6) for k in range(4)]
    edges = []
    for i in range(3):
        shared = np.intersect1d(near[i], near[i + 1])
        edges.append(_edge(i, i + 1, centres, yaws, np.column_stack([shared, shared])))
    ratios = length_ratios(edges, feats, yaws)
    c2, lengths = fit_positions(4, edges, yaws, ratios, np.ones(3, bool))
    spacing = np.linalg.norm(np.diff(c2, axis=0), axis=1)
    np.testing.assert_allclose(spacing / spacing[0], [1.0, 3.0, 2.0], rtol=1e-3)
    assert np.degrees(direction_error(c2, edges, yaws)).max() < 0.01


def test_wrong_direction_stands_out_against_the_consensus():
    rng = np.random.default_rng(2)
    centres = np.array([[0.0, 0, 0], [2.0, 0, 0.5], [1.0, 0, 2.5], [3.0, 0, 3.0]])
    yaws = rng.uniform(-np.pi, np.pi, 4)
    edges = [_edge(i, j, centres, yaws) for i in range(4) for j in range(i + 1, 4)]
    wrong = edges[2]
    wrong.result.pose.phi += np.radians(40.0)
    c2, _ = fit_positions(4, edges, yaws, [], np.ones(len(edges), bool))
    error = np.degrees(direction_error(c2, edges, yaws))
    assert np.argmax(error) == 2
    keep = np.ones(len(edges), bool)
    keep[2] = False
    c2, _ = fit_positions(4, edges, yaws, [], keep)
    assert np.degrees(direction_error(c2, edges, yaws)[keep]).max() < 0.01


def test_tracks_chain_matches_and_drop_conflicts():
    centres = np.zeros((3, 3))
    feats = [(np.eye(3)[[0, 1, 2, 0, 1]], None)] * 3
    edges = [_edge(0, 1, centres + np.arange(3)[:, None], np.zeros(3), np.array([[0, 0], [1, 1], [2, 2]])),
             _edge(1, 2, centres + np.arange(3)[:, None], np.zeros(3), np.array([[0, 0], [1, 3]])),
             # feature 2 of view 0 also matched to feature 4 of view 2, while 2-2 chains to ... a conflict free
             _edge(0, 2, centres + np.arange(3)[:, None], np.zeros(3), np.array([[1, 4]]))]
    tracks = build_tracks(edges, feats)
    # 0: (0,0)-(1,0)-(2,0); 1: (0,1)-(1,1)-(2,3) and (0,1)-(2,4): two features of view 2, dropped; 2: (0,2)-(1,2)
    assert tracks.count == 2
    assert sorted(np.bincount(tracks.point).tolist()) == [2, 3]
    assert components(4, [(0, 1), (1, 2)]) == [[0, 1, 2], [3]]


def test_refinement_recovers_perturbed_poses_and_heights():
    rng = np.random.default_rng(3)
    n = 5
    centres = np.column_stack([rng.uniform(-3, 3, n), rng.uniform(-0.05, 0.05, n), rng.uniform(-2, 2, n)])
    centres[0] = 0.0
    yaws = rng.uniform(-np.pi, np.pi, n)
    yaws[0] = 0.0
    points, feats = _scene(rng, centres, yaws, 300)
    view = np.repeat(np.arange(n), len(points))
    point = np.tile(np.arange(len(points)), n)
    bearing = np.concatenate([f[0] for f in feats])
    bearing = bearing + rng.normal(0, np.radians(0.02), bearing.shape)
    bearing /= np.linalg.norm(bearing, axis=1, keepdims=True)
    tracks = Tracks(view, bearing, point, point.copy(), len(points))
    spread = np.mean(np.linalg.norm(centres - centres.mean(axis=0), axis=1))
    start_c = centres + np.column_stack([rng.normal(0, 0.05, n), np.zeros(n), rng.normal(0, 0.05, n)])
    start_c[0] = 0.0
    start_c[:, 1] = 0.0  # the pair model's one camera height
    start_y = yaws + np.r_[0.0, rng.normal(0, np.radians(0.5), n - 1)]
    start_p = triangulate_tracks(tracks, start_y, start_c)
    y, c, p = refine(tracks, start_y, start_c, start_p, list(range(n)), 0.15)
    scale = spread / np.mean(np.linalg.norm(c - c.mean(axis=0), axis=1))
    assert np.abs(c * scale - centres).max() < 0.01
    assert np.degrees(np.abs(_wrap(y - yaws))).max() < 0.05
    assert np.degrees(np.median(angular_errors(tracks, y, c, p))) < 0.05
