"""Initialisation: 3-NN scales, layout discs along their normal, random points inside the bounds."""

from __future__ import annotations

import math

import numpy as np
import pytest
import shapely
import torch

from gaussians.densify import quat_to_rotmat
from gaussians.init import (
    from_cloud,
    knn_mean_distance,
    quat_with_z_along,
    random_around_cameras,
    random_in_rooms,
    random_points,
    rotation_to_quat,
)
from gaussians.model import sh_to_rgb


def test_knn_mean_distance_matches_brute_force():
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(200, 3))
    d = np.linalg.norm(pts[:, None] - pts[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    expect = np.sort(d, axis=1)[:, :3].mean(1)
    np.testing.assert_allclose(knn_mean_distance(pts), expect, rtol=1e-12)


def test_scales_are_the_mean_3nn_distance_on_a_grid():
    # interior points of a 0.1 m cubic grid: the 3 nearest neighbours are all 0.1 m away
    ax = np.arange(6) * 0.1
    pts = np.stack(np.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    colors = np.tile([[0.2, 0.5, 0.9]], (len(pts), 1))
    g = from_cloud({"points": pts, "colors": colors})
    interior = np.all((pts > 0.05) & (pts < 0.45), axis=1)
    np.testing.assert_allclose(g.scales[interior].numpy(), 0.1, rtol=1e-6)
    assert torch.equal(g.quats, torch.tensor([[1.0, 0, 0, 0]]).expand(len(pts), 4))
    np.testing.assert_allclose(g.opacities.numpy(), 0.1, rtol=1e-6)
    np.testing.assert_allclose(sh_to_rgb(g.sh_dc[:, 0]).numpy(), colors, atol=1e-6)
    assert g.sh_degree == 3 and torch.all(g.sh_rest == 0)
    assert not g.is_layout.any() and torch.equal(g.u0, g.means)


def test_duplicate_points_get_a_positive_scale():
    g = from_cloud({"points": np.zeros((5, 3)), "colors": np.zeros((5, 3))})
    assert torch.all(torch.isfinite(g.log_scales)) and torch.all(g.scales > 0)


def test_rotation_to_quat_round_trip():
    rng = np.random.default_rng(3)
    q = rng.normal(size=(500, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    r = quat_to_rotmat(torch.from_numpy(q)).numpy()
    q2 = rotation_to_quat(r)
    q = np.where(q[:, :1] < 0, -q, q)
    np.testing.assert_allclose(q2, q, atol=1e-9)


def test_layout_points_are_discs_in_their_plane():
    normals = np.array([[0, 1.0, 0], [0, -1.0, 0], [1.0, 0, 0], [0, 0, -1.0], [0.6, 0, 0.8]])
    q = quat_with_z_along(normals)
    r = quat_to_rotmat(torch.from_numpy(q)).numpy()
    np.testing.assert_allclose(r[:, :, 2], normals, atol=1e-12)  # local z -> normal

    # a floor patch (layout, normal up = -y) next to free depth points
    ax = np.arange(5) * 0.2
    xx, zz = np.meshgrid(ax, ax)
    floor = np.stack([xx.ravel(), np.zeros(xx.size), zz.ravel()], 1)
    depth = floor[:4] + [0.0, -1.0, 0.0]
    pts = np.concatenate([floor, depth])
    nrm = np.concatenate([np.tile([[0, -1.0, 0]], (len(floor), 1)), np.zeros((4, 3))])
    lay = np.arange(len(pts)) < len(floor)
    g = from_cloud({"points": pts, "colors": np.full((len(pts), 3), 0.5), "normals": nrm, "u0": pts,
                    "is_layout": lay}, layout_flatten=0.1)
    assert torch.equal(g.is_layout, torch.from_numpy(lay))
    rot = quat_to_rotmat(g.quats)
    s = g.scales
    # world covariance: thin along the normal, wide in the plane
    cov = rot @ torch.diag_embed(s * s) @ rot.transpose(1, 2)
    n = torch.tensor([0, -1.0, 0])
    along = torch.einsum("i,nij,j->n", n, cov, n).sqrt()
    inplane = torch.einsum("i,nij,j->n", torch.tensor([1.0, 0, 0]), cov, torch.tensor([1.0, 0, 0])).sqrt()
    np.testing.assert_allclose((along / inplane)[: len(floor)].numpy(), 0.1, rtol=1e-5)
    np.testing.assert_allclose((along / inplane)[len(floor):].numpy(), 1.0, rtol=1e-5)
    np.testing.assert_allclose(g.normals[: len(floor)].numpy(), nrm[: len(floor)])
    assert torch.all(g.normals[len(floor):] == 0)


def test_random_points_fill_an_l_shaped_room():
    room = {"polygon": [[0, 0], [4, 0], [4, 2], [2, 2], [2, 4], [0, 4]], "floor_y": 0.0, "ceiling_y": -2.5}
    rng = np.random.default_rng(0)
    pts = random_in_rooms([room], 4000, rng)
    assert pts.shape == (4000, 3)
    poly = shapely.Polygon(room["polygon"])
    assert shapely.contains_xy(poly, pts[:, 0], pts[:, 2]).all()
    assert pts[:, 1].min() >= -2.5 and pts[:, 1].max() <= 0.0
    # uniform: three quarters of the L's area lie outside the square [2,4]x[2,4] hole... a third per arm
    share = np.mean((pts[:, 0] < 2) & (pts[:, 2] < 2))
    assert abs(share - 1 / 3) < 0.04


def test_random_points_around_cameras_and_determinism():
    cams = np.array([[0.0, -1.5, 0.0], [1.0, -1.5, 2.0]])
    pts = random_around_cameras(cams, 2000, np.random.default_rng(0), margin=3.0, vertical=1.5)
    assert pts[:, 0].min() >= -3 and pts[:, 0].max() <= 4
    assert pts[:, 1].min() >= -3 and pts[:, 1].max() <= 0
    a = random_points(300, seed=7, camera_positions=cams)
    b = random_points(300, seed=7, camera_positions=cams)
    assert torch.equal(a.means, b.means) and torch.equal(a.sh_dc, b.sh_dc)
    with pytest.raises(ValueError):
        random_points(10, seed=0)
    assert math.isclose(float(a.opacities[0]), 0.1, rel_tol=1e-6)
