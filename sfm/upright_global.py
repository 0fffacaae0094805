"""Poses of N levelled panoramas (gravity known): the upright pair solver on chosen pairs, then a
global solve.

The global SfM systems (COLMAP 4's global mapper, GLOMAP, Theia, OpenMVG) share one outline:
verified pairs, rotation averaging, translation averaging with outlier rejection,
triangulation, bundle adjustment. With levelled 360° cameras every step gets smaller:

1. **Features** once per panorama (sfm.upright_pair: RootSIFT on the rig views).
2. **Pairs worth solving**: with few panoramas all of them; as N grows, each panorama's
   `neighbours` most similar ones, similarity being the number of mutual ratio-test matches
   among the `similarity_features` strongest features of each (a vocabulary tree would do
   for thousands; tens of panoramas need no index).
3. **Pair poses**: sfm.upright_pair's exhaustive (yaw, baseline azimuth) search, verified by
   its distinctness and inlier count.
4. **Yaw averaging**: a rotation is one angle, so a pair says yaw_j - yaw_i = theta_ij.
   Random spanning trees (weighted by inliers) propose yaws, the one most pairs agree with
   within `yaw_tolerance_deg` wins (cycle consistency, RANSAC style), then least squares
   over the agreeing pairs.
5. **Positions**: a pair gives the horizontal direction between two centres, not the
   distance. Pairs that share a panorama and tracks give the ratio of their lengths (the
   depths of the shared points from the common panorama), so a chain of nearly collinear
   panoramas, where directions alone fix nothing, still gets its lengths. One robust
   least-squares (soft L1) fits centres and log lengths to both; pairs whose direction then
   disagrees by more than `direction_tolerance_deg` are dropped (the 1DSfM/BATA idea:
   judge a direction against the consensus) and the fit repeated.
6. **Triangulation** of tracks (matches chained through shared features, union-find),
   every ray within `track_tolerance_deg` of its point.
7. **Joint refinement** (bundle adjustment): yaw and 3D centre of every panorama and every
   point, minimising the robust (Huber) angular error of every observation
   (Levenberg-Marquardt, points eliminated by the Schur complement); the cameras stay
   level. Camera heights may then differ a little, which the pair model (one height)
   could not express.

The largest connected set of panoramas is kept; the others are named with the reason.
Scale: one unit is the mean distance of the centres from their mean; sfm.frame makes it metric.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components, minimum_spanning_tree

from sfm.records import Panorama, Reconstruction
from sfm.rig import rotation_about_y
from sfm.upright_pair import (PairResult, UprightPairOptions, bearing_color, two_nearest, descriptor_distance, features,
                              pose_from_features)


@dataclass
class UprightGlobalOptions:
    pair: UprightPairOptions = field(default_factory=UprightPairOptions)
    #: up to this many panoramas every pair is solved; above it, the `neighbours` most similar per panorama
    all_pairs_up_to: int = 6
    neighbours: int = 4
    similarity_features: int = 1500
    #: pairs with fewer mutual matches among the strongest features are not worth a search
    min_similarity: int = 12
    yaw_tolerance_deg: float = 2.0
    direction_tolerance_deg: float = 5.0
    track_tolerance_deg: float = 1.0
    #: Huber scale of the angular error in the joint refinement
    refine_scale_deg: float = 0.15
    #: observations this far from their point after the first refinement are dropped before the second
    refine_drop_deg: float = 0.6
    #: points whose rays meet at a smaller angle are left out of the sparse cloud
    min_triangulation_deg: float = 3.0
    seed: int = 0
    threads: int = 2


@dataclass
class PairEdge:
    """A verified pair: view indices i < j and the pair solver's result (j relative to i)."""

    i: int
    j: int
    result: PairResult

    @property
    def inliers(self) -> int:
        return self.result.inliers


@dataclass
class GlobalResult:
    reconstruction: Reconstruction
    #: every pair solved: (view a, view b, inliers or 0 when not verified, kept by the global solve)
    pairs: list[tuple[str, str, int, bool]]
    #: views left out -> why
    left_out: dict[str, str]
    candidates: int
    #: median angular error of the observations after the refinement (degrees)
    residual_deg: float


def _wrap(x: np.ndarray | float) -> np.ndarray | float:
    return (np.asarray(x) + np.pi) % (2 * np.pi) - np.pi


def similarity(feats: list[tuple[np.ndarray, np.ndarray]], count: int, ratio: float = 0.8) -> np.ndarray:
    """[N,N] mutual nearest-neighbour matches passing a ratio test among each panorama's `count`
    strongest features (symmetric, zero diagonal)."""
    n = len(feats)
    out = np.zeros((n, n), int)
    subset = [d[:count] for _, d in feats]
    for i in range(n):
        for j in range(i + 1, n):
            if len(subset[i]) < 2 or len(subset[j]) < 2:
                continue
            distance = descriptor_distance(subset[i], subset[j])
            fwd, bwd = two_nearest(distance), two_nearest(distance.T)
            rows = np.arange(len(fwd))
            good = distance[rows, fwd[:, 0]] < ratio * distance[rows, fwd[:, 1]]
            cols = np.arange(len(bwd))
            back_ok = distance[bwd[:, 0], cols] < ratio * distance[bwd[:, 1], cols]
            mutual = bwd[fwd[:, 0], 0] == rows
            out[i, j] = out[j, i] = int(np.sum(good & mutual & back_ok[fwd[:, 0]]))
    return out


def candidate_pairs(sim: np.ndarray, options: UprightGlobalOptions) -> list[tuple[int, int]]:
    """Pairs to solve, most similar first: every pair for a few panoramas, else each panorama's
    `neighbours` most similar ones (above `min_similarity`)."""
    n = len(sim)
    if n <= options.all_pairs_up_to:
        pairs = {(i, j) for i in range(n) for j in range(i + 1, n)}
    else:
        pairs = set()
        for i in range(n):
            for j in np.argsort(-sim[i], kind="stable")[: options.neighbours]:
                if j != i and sim[i, j] >= options.min_similarity:
                    pairs.add((min(i, int(j)), max(i, int(j))))
    return sorted(pairs, key=lambda p: -sim[p])


# ----------------------------------------------------------------------------- yaw averaging


def average_yaws(n: int, edges: list[tuple[int, int, float, float]], tolerance: float, seed: int = 0,
                 trials: int = 50) -> tuple[np.ndarray, np.ndarray]:
    """Yaws [n] (yaw 0 of the first panorama each component reaches is 0) from pairs (i, j,
    theta_ij = yaw_j - yaw_i, weight) and which pairs agree (within `tolerance`, radians).
    Hypotheses are random spanning trees drawn with weight-biased edge order; the one the most
    pairs agree with is refined by least squares over the agreeing pairs."""
    rng = np.random.default_rng(seed)
    weights = np.array([e[3] for e in edges], float)
    best, best_score = None, -1.0
    for trial in range(trials):
        # Kruskal: the maximum spanning tree first, then perturbed weights and plain random orders
        # (a strong wrong pair must be left out of some trees)
        keys = (weights if trial == 0 else weights * rng.uniform(0.2, 1.0, len(weights)) if trial % 2
                else rng.uniform(size=len(weights)))
        yaw = _tree_yaws(n, edges, np.argsort(-keys, kind="stable"))
        residual = np.array([abs(_wrap(yaw[j] - yaw[i] - t)) for i, j, t, _ in edges])
        agree = residual < tolerance
        # consensus first (how many pairs agree), their inliers only between equals: one strong
        # wrong pair must not outvote several weaker right ones
        score = float(agree.sum()) + float(weights[agree].sum()) / (1.0 + float(weights.sum()))
        if score > best_score:
            best, best_score = (yaw, agree), score
    yaw, agree = best
    # least squares about the hypothesis: yaw = yaw0 + delta, one gauge per component
    kept = [e for e, a in zip(edges, agree) if a]
    if kept:
        rows = len(kept)
        a = np.zeros((rows + n, n))
        b = np.zeros(rows + n)
        for r, (i, j, t, w) in enumerate(kept):
            s = np.sqrt(w)
            a[r, j], a[r, i] = s, -s
            b[r] = -s * _wrap(yaw[j] - yaw[i] - t)
        # a weak prior on every delta fixes each component's gauge without pulling on the pairs
        a[rows:] = 1e-6 * np.eye(n)
        delta = np.linalg.lstsq(a, b, rcond=None)[0]
        yaw = _wrap(yaw + delta)
        residual = np.array([abs(_wrap(yaw[j] - yaw[i] - t)) for i, j, t, _ in edges])
        agree = residual < tolerance
    return yaw, agree


def _tree_yaws(n: int, edges, order) -> np.ndarray:
    """Yaws along the spanning forest Kruskal builds taking the edges in `order`: scipy's minimum
    spanning forest over their ranks (distinct, so the forest is that one)."""
    rank = np.zeros((n, n))
    for r, k in enumerate(order, start=1):
        i, j = sorted(edges[k][:2])
        if rank[i, j] == 0:  # of two pairs between the same views, the earlier one
            rank[i, j] = r
    forest = minimum_spanning_tree(rank).tocoo()
    by_rank = {r: k for r, k in enumerate(order, start=1)}
    adjacency: dict[int, list[tuple[int, float]]] = {k: [] for k in range(n)}
    for r in forest.data.astype(int):
        i, j, t, _ = edges[by_rank[r]]
        adjacency[i].append((j, t))
        adjacency[j].append((i, -t))
    yaw = np.full(n, np.nan)
    for start in range(n):
        if not np.isnan(yaw[start]):
            continue
        yaw[start] = 0.0
        stack = [start]
        while stack:
            u = stack.pop()
            for v, t in adjacency[u]:
                if np.isnan(yaw[v]):
                    yaw[v] = _wrap(yaw[u] + t)
                    stack.append(v)
    return yaw


# ----------------------------------------------------------------------------- positions


def components(n: int, edges: Sequence[tuple[int, int]]) -> list[list[int]]:
    """Connected components of the views under `edges`, largest first (ties: lowest view first)."""
    labels = _component_labels(n, edges)
    out = [np.flatnonzero(labels == c).tolist() for c in np.unique(labels)]
    return sorted(out, key=lambda c: (-len(c), c[0]))


def _component_labels(n: int, edges: Sequence[tuple[int, int]]) -> np.ndarray:
    """[n] connected-component label of each node under `edges` (scipy.sparse.csgraph)."""
    ij = np.asarray(list(edges), int).reshape(-1, 2)
    graph = coo_matrix((np.ones(len(ij)), (ij[:, 0], ij[:, 1])), shape=(n, n))
    return connected_components(graph, directed=False)[1]


def length_ratios(edges: list[PairEdge], feats: list[tuple[np.ndarray, np.ndarray]],
                  yaw: np.ndarray) -> list[tuple[int, int, float]]:
    """(edge a, edge b, log(length_a / length_b)) for pairs of edges sharing a view and at
    least 5 matched features in it: the median ratio of the shared points' depths from that view
    (each pair's points are triangulated with its own baseline of length 1)."""
    depth: list[dict[int, dict[int, float]]] = []  # per edge: view -> feature -> depth (baseline units)
    for e in edges:
        r = e.result
        b1 = feats[e.i][0][r.matches[:, 0]]
        w2 = feats[e.j][0][r.matches[:, 1]] @ r.pose.a_from_b[:3, :3].T
        c = r.pose.baseline
        ab, ac, bc = np.sum(b1 * w2, axis=1), b1 @ c, w2 @ c
        den = np.maximum(1.0 - ab**2, 1e-12)
        l1, l2 = (ac - ab * bc) / den, (ab * ac - bc) / den
        depth.append({e.i: dict(zip(r.matches[:, 0].tolist(), l1.tolist())),
                      e.j: dict(zip(r.matches[:, 1].tolist(), l2.tolist()))})
    out = []
    for a in range(len(edges)):
        for b in range(a + 1, len(edges)):
            for view in {edges[a].i, edges[a].j} & {edges[b].i, edges[b].j}:
                da, db = depth[a][view], depth[b][view]
                shared = [f for f in da if f in db and da[f] > 0 and db[f] > 0]
                if len(shared) >= 5:
                    # a point at depth D from the shared view: D = la * length_a = lb * length_b
                    ratio = np.median([db[f] / da[f] for f in shared])
                    out.append((a, b, float(np.log(ratio))))
    return out


def fit_positions(n: int, edges: list[PairEdge], yaw: np.ndarray, ratios: list[tuple[int, int, float]],
                  active: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Horizontal centres [n,2] (x, z) and lengths [edges] fitting the active edges' world
    directions and the length ratios, robustly (soft L1); the first view of the edges sits at
    the origin and the mean log length is 0."""
    idx = np.flatnonzero(active)
    dirs = np.zeros((len(edges), 2))
    for k, e in enumerate(edges):
        world = rotation_about_y(np.degrees(yaw[e.i])) @ e.result.pose.baseline
        dirs[k] = world[[0, 2]]
    views = sorted({e.i for e in np.array(edges, object)[idx]} | {e.j for e in np.array(edges, object)[idx]})
    anchor = views[0]
    free = [v for v in views if v != anchor]
    col = {v: k for k, v in enumerate(free)}
    used_ratios = [(a, b, r) for a, b, r in ratios if active[a] and active[b]]
    pos_e = {e: k for k, e in enumerate(idx)}

    def unpack(x):
        c = np.zeros((n, 2))
        for v in free:
            c[v] = x[2 * col[v]:2 * col[v] + 2]
        return c, x[2 * len(free):]

    def residuals(x):
        c, loglen = unpack(x)
        out = []
        length = np.exp(loglen)
        for k, e in enumerate(idx):
            ed = edges[e]
            out.append(c[ed.j] - c[ed.i] - length[k] * dirs[e])
        res = [np.concatenate(out) if out else np.zeros(0)]
        if used_ratios:
            res.append(np.array([loglen[pos_e[a]] - loglen[pos_e[b]] - r for a, b, r in used_ratios]))
        res.append(np.array([10.0 * loglen.mean()]))
        return np.concatenate(res)

    # start: lengths 1 along a breadth-first tree
    x0 = np.zeros(2 * len(free) + len(idx))
    c0 = {anchor: np.zeros(2)}
    changed = True
    while changed:
        changed = False
        for e in idx:
            ed = edges[e]
            if ed.i in c0 and ed.j not in c0:
                c0[ed.j] = c0[ed.i] + dirs[e]
                changed = True
            elif ed.j in c0 and ed.i not in c0:
                c0[ed.i] = c0[ed.j] - dirs[e]
                changed = True
    for v in free:
        x0[2 * col[v]:2 * col[v] + 2] = c0.get(v, np.zeros(2))
    fit = least_squares(residuals, x0, loss="soft_l1", f_scale=0.05)
    c, loglen = unpack(fit.x)
    lengths = np.full(len(edges), np.nan)
    lengths[idx] = np.exp(loglen)
    return c, lengths


def direction_error(c: np.ndarray, edges: list[PairEdge], yaw: np.ndarray) -> np.ndarray:
    """[edges] angle (radians) between each pair's measured world direction and its fitted centres'."""
    out = np.zeros(len(edges))
    for k, e in enumerate(edges):
        d = rotation_about_y(np.degrees(yaw[e.i])) @ e.result.pose.baseline
        f = c[e.j] - c[e.i]
        norm = np.linalg.norm(f)
        out[k] = np.pi if norm == 0 else np.arccos(np.clip(d[[0, 2]] @ f / norm, -1.0, 1.0))
    return out


# ----------------------------------------------------------------------------- tracks


@dataclass
class Tracks:
    view: np.ndarray  # [M] observation -> view index
    bearing: np.ndarray  # [M,3] unit bearing in the view's frame
    point: np.ndarray  # [M] observation -> point index
    feature: np.ndarray  # [M] feature index in its view
    count: int


def build_tracks(edges: list[PairEdge], feats: list[tuple[np.ndarray, np.ndarray]]) -> Tracks:
    """Chain the pairs' inlier matches into tracks (union-find over (view, feature)); a track
    holding two features of one view is dropped (a wrong match somewhere along it)."""
    ids: dict[tuple[int, int], int] = {}  # (view, feature) -> node, numbered as first matched
    links = []
    for e in edges:
        for fa, fb in e.result.matches.tolist():
            links.append((ids.setdefault((e.i, fa), len(ids)), ids.setdefault((e.j, fb), len(ids))))
    labels = _component_labels(len(ids), links)
    # tracks in the order of their first node, members in node order
    groups: dict[int, list[tuple[int, int]]] = {}
    for key, k in ids.items():
        groups.setdefault(int(labels[k]), []).append(key)
    view, feature, point = [], [], []
    count = 0
    for members in groups.values():
        seen_views = [v for v, _ in members]
        if len(set(seen_views)) != len(seen_views) or len(members) < 2:
            continue
        for v, f in members:
            view.append(v)
            feature.append(f)
            point.append(count)
        count += 1
    view_a, feature_a = np.array(view, int), np.array(feature, int)
    bearing = np.array([feats[v][0][f] for v, f in zip(view, feature)]).reshape(-1, 3)
    return Tracks(view_a, bearing, np.array(point, int), feature_a, count)


def _world_rays(tracks: Tracks, yaw: np.ndarray, centres: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    c, s = np.cos(yaw[tracks.view]), np.sin(yaw[tracks.view])
    b = tracks.bearing
    # rotation_about_y(yaw) @ b, vectorised
    d = np.column_stack([c * b[:, 0] + s * b[:, 2], b[:, 1], -s * b[:, 0] + c * b[:, 2]])
    return centres[tracks.view], d


def triangulate_tracks(tracks: Tracks, yaw: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """[points,3]: per track the point closest (least squares) to its rays."""
    origin, d = _world_rays(tracks, yaw, centres)
    proj = np.eye(3)[None] - d[:, :, None] * d[:, None, :]  # I - d d^T per observation
    a = np.zeros((tracks.count, 3, 3))
    b = np.zeros((tracks.count, 3))
    np.add.at(a, tracks.point, proj)
    np.add.at(b, tracks.point, np.einsum("nij,nj->ni", proj, origin))
    a += 1e-9 * np.eye(3)
    return np.linalg.solve(a, b[..., None])[..., 0]


def angular_errors(tracks: Tracks, yaw: np.ndarray, centres: np.ndarray, points: np.ndarray) -> np.ndarray:
    """[observations] angle (radians) between each observed ray and the ray to its point; rays
    pointing away from the point count as pi."""
    origin, d = _world_rays(tracks, yaw, centres)
    to_point = points[tracks.point] - origin
    cos = np.sum(d * to_point, axis=1) / np.maximum(np.linalg.norm(to_point, axis=1), 1e-12)
    return np.arccos(np.clip(cos, -1.0, 1.0))


def triangulation_angles(tracks: Tracks, yaw: np.ndarray, centres: np.ndarray, points: np.ndarray) -> np.ndarray:
    """[points] the largest angle (radians) at each point between the rays from its cameras."""
    origin, _ = _world_rays(tracks, yaw, centres)
    v = points[tracks.point] - origin
    v /= np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)
    # the largest angle to the first ray of the track is within a factor 2 of the largest pairwise one
    first = np.full(tracks.count, -1)
    first[tracks.point[::-1]] = np.arange(len(tracks.point))[::-1]
    cos = np.sum(v * v[first[tracks.point]], axis=1)
    out = np.zeros(tracks.count)
    np.maximum.at(out, tracks.point, np.arccos(np.clip(cos, -1.0, 1.0)))
    return out


def keep_observations(tracks: Tracks, keep: np.ndarray) -> Tracks:
    """The observations `keep` [M] bool; points left with fewer than two views are dropped."""
    point = tracks.point[keep]
    counts = np.bincount(point, minlength=tracks.count)
    ok = counts[point] >= 2
    kept_points = np.unique(point[ok])
    renumber = np.full(tracks.count, -1)
    renumber[kept_points] = np.arange(len(kept_points))
    sel = np.flatnonzero(keep)[ok]
    return Tracks(tracks.view[sel], tracks.bearing[sel], renumber[tracks.point[sel]], tracks.feature[sel],
                  len(kept_points))


# ----------------------------------------------------------------------------- refinement


def refine(tracks: Tracks, yaw: np.ndarray, centres: np.ndarray, points: np.ndarray, views: list[int],
           scale_deg: float, iterations: int = 30) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bundle adjustment in the upright parametrisation: the yaws, 3D centres and points of `views`
    (the first fixed) minimising the observations' angular errors (Huber at `scale_deg`, by
    iteratively reweighted Levenberg-Marquardt with the points eliminated by the Schur
    complement: the camera system is 4 x views square). The residual of an observation is
    normalise(X - c) - R(yaw) b in the world (its norm is the angle, to first order). The scale,
    free in bearings, is held by rescaling about the first camera after every step."""
    free = list(views[1:])
    index = np.full(len(yaw), -1)
    index[free] = np.arange(len(free))
    nf = len(free)
    cam = index[tracks.view]  # -1: the fixed camera
    has = cam >= 0
    point = tracks.point
    counts = np.bincount(point, minlength=tracks.count)
    order = np.argsort(point, kind="stable")
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    # every ordered pair of observations of one point (their cameras couple through it)
    reps = counts[point[order]]
    first = np.repeat(order, reps)
    offsets = np.arange(len(first)) - np.repeat(np.cumsum(reps) - reps, reps)
    second = order[np.repeat(starts[point[order]], reps) + offsets]
    pair_ok = has[first] & has[second]
    first, second = first[pair_ok], second[pair_ok]
    anchor = views[0]
    spread0 = float(np.mean(np.linalg.norm(centres[views] - centres[views].mean(axis=0), axis=1)))
    k = np.radians(scale_deg)

    def evaluate(y, c, p):
        origin, d = _world_rays(tracks, y, c)
        v = p[point] - origin
        norm = np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)
        u = v / norm
        return u - d, u, norm, d

    def cost(r):
        e = np.linalg.norm(r, axis=1)
        return float(np.sum(np.where(e < k, e**2, 2 * k * e - k**2)))

    y, c, p = yaw.copy(), centres.copy(), points.copy()
    r, u, norm, d = evaluate(y, c, p)
    current = cost(r)
    lam = 1e-3
    for _ in range(iterations):
        e = np.linalg.norm(r, axis=1)
        w = np.sqrt(np.where(e < k, 1.0, k / np.maximum(e, 1e-15)))[:, None]  # Huber as reweighting
        jp = (np.eye(3)[None] - u[:, :, None] * u[:, None, :]) / norm[:, :, None]  # d r / d X
        cy, sy = np.cos(y[tracks.view]), np.sin(y[tracks.view])
        b = tracks.bearing
        dyaw = -np.column_stack([-sy * b[:, 0] + cy * b[:, 2], np.zeros(len(b)), -cy * b[:, 0] - sy * b[:, 2]])
        jc = np.concatenate([dyaw[:, :, None], -jp], axis=2)  # [M,3,4]: yaw, centre
        jp, jc, rw = jp * w[:, :, None], jc * w[:, :, None], r * w
        u_blocks = np.zeros((nf, 4, 4))
        np.add.at(u_blocks, cam[has], np.einsum("mai,maj->mij", jc[has], jc[has]))
        v_blocks = np.zeros((tracks.count, 3, 3))
        np.add.at(v_blocks, point, np.einsum("mai,maj->mij", jp, jp))
        w_blocks = np.einsum("mai,maj->mij", jc, jp)  # [M,4,3]
        g_c = np.zeros((nf, 4))
        np.add.at(g_c, cam[has], np.einsum("mai,ma->mi", jc[has], rw[has]))
        g_p = np.zeros((tracks.count, 3))
        np.add.at(g_p, point, np.einsum("mai,ma->mi", jp, rw))
        while True:
            v_damped = v_blocks + lam * (v_blocks * np.eye(3)[None] + 1e-9 * np.eye(3)[None])
            v_inv = np.linalg.inv(v_damped)
            y_obs = np.einsum("mij,mjk->mik", w_blocks, v_inv[point])  # W V^-1 per observation
            s_mat = np.zeros((nf, nf, 4, 4))
            np.add.at(s_mat, (cam[first], cam[second]),
                      -np.einsum("mij,mkj->mik", y_obs[first], w_blocks[second]))
            s_mat = s_mat.transpose(0, 2, 1, 3).reshape(4 * nf, 4 * nf)
            u_damped = u_blocks + lam * (u_blocks * np.eye(4)[None] + 1e-9 * np.eye(4)[None])
            for q in range(nf):
                s_mat[4 * q:4 * q + 4, 4 * q:4 * q + 4] += u_damped[q]
            rhs = -g_c.copy()
            np.add.at(rhs, cam[has], np.einsum("mij,mj->mi", y_obs[has], g_p[point[has]]))
            try:
                delta_c = np.linalg.solve(s_mat, rhs.ravel()).reshape(nf, 4) if nf else np.zeros((0, 4))
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            wt_dc = np.zeros((tracks.count, 3))
            np.add.at(wt_dc, point[has], np.einsum("mij,mi->mj", w_blocks[has], delta_c[cam[has]]))
            delta_p = np.einsum("pij,pj->pi", v_inv, -g_p - wt_dc)
            y_new, c_new = y.copy(), c.copy()
            y_new[free] += delta_c[:, 0]
            c_new[free] += delta_c[:, 1:]
            p_new = p + delta_p
            # the scale is free: hold the cameras' spread, about the fixed camera
            spread = float(np.mean(np.linalg.norm(c_new[views] - c_new[views].mean(axis=0), axis=1)))
            f = spread0 / spread
            c_new = c[anchor] + (c_new - c[anchor]) * f
            p_new = c[anchor] + (p_new - c[anchor]) * f
            r_new, u_new, norm_new, d_new = evaluate(y_new, c_new, p_new)
            new = cost(r_new)
            if new < current:
                y, c, p, r, u, norm, d = y_new, c_new, p_new, r_new, u_new, norm_new, d_new
                improvement = (current - new) / max(current, 1e-30)
                current, lam = new, max(lam / 10, 1e-9)
                break
            lam *= 10
            if lam > 1e8:
                improvement = 0.0
                break
        if improvement < 1e-7:
            break
    return _wrap(y), c, p


# ----------------------------------------------------------------------------- the solver


@contextmanager
def _timed(timings: dict[str, float], step: str):
    """Adds the wall seconds of the block to timings[step]."""
    t0 = time.perf_counter()
    try:
        yield
    finally:
        timings[step] = timings.get(step, 0.0) + time.perf_counter() - t0


def solve(panoramas: Sequence[Panorama], options: UprightGlobalOptions | None = None,
          progress: Callable[[str, int, int], None] = lambda step, done, total: None) -> GlobalResult:
    """Poses of `panoramas` (levelled, one size) as a Reconstruction in an upright frame (y down,
    the first placed panorama at the origin, mean centre spread 1); views it cannot place are in
    `left_out` with the reason."""
    options = options or UprightGlobalOptions()
    names = [p.name for p in panoramas]
    n = len(panoramas)
    timings: dict[str, float] = {}

    with _timed(timings, "features"):
        done = [0]

        def extract(p):
            out = features(p, options.pair)
            done[0] += 1
            progress("features", done[0], n)
            return out

        with ThreadPoolExecutor(max(1, options.threads)) as pool:  # OpenCV releases the GIL
            feats = list(pool.map(extract, panoramas))

    with _timed(timings, "similarity"):
        sim = similarity(feats, options.similarity_features)
        candidates = candidate_pairs(sim, options)

    with _timed(timings, "pairs"):
        edges: list[PairEdge] = []
        tried: dict[tuple[int, int], int] = {}

        def solve_pair(pair):
            i, j = pair
            return pair, pose_from_features(panoramas[i], panoramas[j], feats[i], feats[j], options.pair)

        finished = [0]
        with ThreadPoolExecutor(max(1, options.threads)) as pool:  # numpy releases the GIL in its kernels
            for (i, j), result in pool.map(solve_pair, candidates):
                finished[0] += 1
                progress("pairs", finished[0], len(candidates))
                tried[(i, j)] = 0 if result is None else result.inliers
                if result is not None:
                    edges.append(PairEdge(i, j, result))

    with _timed(timings, "averaging"):
        left_out: dict[str, str] = {}
        verified = {v for e in edges for v in (e.i, e.j)}
        for v in range(n):
            if v not in verified:
                left_out[names[v]] = "no verified pair" if any(v in p for p in candidates) else \
                    "no similar panorama (no candidate pair)"
        kept = np.zeros(len(edges), bool)
        yaw = np.zeros(n)
        centres = np.zeros((n, 3))
        c2 = np.zeros((n, 2))
        if edges:
            yaw, kept = average_yaws(n, [(e.i, e.j, e.result.pose.theta, float(e.inliers)) for e in edges],
                                     np.radians(options.yaw_tolerance_deg), options.seed)
            ratios = length_ratios(edges, feats, yaw)
            for _ in range(len(edges)):
                if not kept.any():
                    break
                # the largest component of the kept pairs is placed; the others fall out below
                comp = components(n, [(edges[k].i, edges[k].j) for k in np.flatnonzero(kept)])[0]
                active = kept & np.array([e.i in comp for e in edges])
                c2, _ = fit_positions(n, edges, yaw, ratios, active)
                error = direction_error(c2, edges, yaw)
                worst = np.flatnonzero(active)[np.argmax(error[active])]
                if error[worst] <= np.radians(options.direction_tolerance_deg):
                    kept = active
                    break
                kept[worst] = False  # one at a time: a wrong pair drags its neighbours' fit too
            centres[:, 0], centres[:, 2] = c2[:, 0], c2[:, 1]

    comps = components(n, [(edges[k].i, edges[k].j) for k in np.flatnonzero(kept)])
    placed = comps[0] if comps and len(comps[0]) >= 2 else []
    for v in range(n):
        if v not in placed and names[v] not in left_out:
            left_out[names[v]] = ("its pairs disagree with the others (yaw or direction)"
                                  if any(v in (e.i, e.j) for e in edges) else "no verified pair")
            if any(v in (edges[k].i, edges[k].j) for k in np.flatnonzero(kept)):
                left_out[names[v]] = "verified pairs only with views outside the largest connected group"
    pairs_report = [(names[i], names[j], tried[(i, j)],
                     any(kept[k] for k, e in enumerate(edges) if (e.i, e.j) == (i, j)) and i in placed)
                    for i, j in candidates]

    def unplaced() -> GlobalResult:  # nothing placed: the pairs and the reasons only
        empty = Reconstruction({}, {}, {}, np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros(0, int),
                               len(edges), 0, timings)
        return GlobalResult(empty, pairs_report, left_out, len(candidates), float("nan"))

    if len(placed) < 2:
        return unplaced()

    with _timed(timings, "triangulation"):
        used = [e for k, e in enumerate(edges) if kept[k] and e.i in placed]
        tracks = build_tracks(used, feats)
        # the frame: the first placed view at the origin, mean spread of the centres 1
        centres = centres - centres[placed[0]]
        spread = float(np.mean(np.linalg.norm(centres[placed] - centres[placed].mean(axis=0), axis=1)))
        if not np.isfinite(spread) or spread <= 0:  # the directions did not separate the centres
            return unplaced()
        centres /= spread
        points = triangulate_tracks(tracks, yaw, centres)
        error = angular_errors(tracks, yaw, centres, points)
        tracks = keep_observations(tracks, error < np.radians(max(options.track_tolerance_deg, 3.0)))
        points = triangulate_tracks(tracks, yaw, centres)

    with _timed(timings, "refinement"):
        for step in range(2):
            yaw, centres, points = refine(tracks, yaw, centres, points, placed, options.refine_scale_deg)
            error = angular_errors(tracks, yaw, centres, points)
            limit = options.refine_drop_deg if step == 0 else options.track_tolerance_deg
            tracks = keep_observations(tracks, error < np.radians(limit))
            points = triangulate_tracks(tracks, yaw, centres)
    error = np.degrees(angular_errors(tracks, yaw, centres, points))
    median_error = float(np.median(error))
    # points seen under a small angle are poorly placed along their rays: far from every camera,
    # they would mislead the floor fit (sfm.frame) and clutter the sparse cloud
    well = triangulation_angles(tracks, yaw, centres, points) >= np.radians(options.min_triangulation_deg)
    tracks = keep_observations(tracks, well[tracks.point])
    points = triangulate_tracks(tracks, yaw, centres)
    error = np.degrees(angular_errors(tracks, yaw, centres, points))

    width = panoramas[0].rgb.shape[1]
    px_per_deg = width / 360.0
    cam_from_world, reproj, observations = {}, {}, {}
    for v in placed:
        pose = np.eye(4)
        pose[:3, :3] = rotation_about_y(np.degrees(yaw[v]))
        pose[:3, 3] = centres[v]
        cam_from_world[names[v]] = np.linalg.inv(pose)
        mine = tracks.view == v
        reproj[names[v]] = float(error[mine].mean() * px_per_deg) if mine.any() else 0.0
        observations[names[v]] = int(mine.sum())
    colors = np.zeros((tracks.count, 3), np.uint8)
    first = np.unique(tracks.point, return_index=True)[1]
    for k in first:
        colors[tracks.point[k]] = bearing_color(panoramas[tracks.view[k]], tracks.bearing[k])
    track_length = np.bincount(tracks.point, minlength=tracks.count)
    seen_by = {names[v]: np.unique(tracks.point[tracks.view == v]) for v in placed}
    recon = Reconstruction(cam_from_world, reproj, observations, points, colors, track_length,
                           sum(r[3] for r in pairs_report), 1, timings, seen_by)
    return GlobalResult(recon, pairs_report, left_out, len(candidates), median_error)
