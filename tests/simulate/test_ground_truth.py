"""Ground truth written by the simulator is exact and self-consistent.

These tests read the scene folder from disk and use only DESIGN.md's conventions
(panogeom.equirect), not the simulator's internals.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from panogeom.equirect import angles_to_pixel, dirs_to_angles, pixel_grid_angles, ray_directions
from simulate.layout import horizonnet_to_boundary

PRESETS = ["cuboid", "l-shape", "two-rooms", "demo", "suite"]


def world_points(scene, view):
    d = scene.depth(view.name).astype(np.float64)
    h, w = d.shape
    rays = ray_directions(h, w)
    pose = view.pose_matrix
    return (rays * d[..., None]) @ pose[:3, :3].T + pose[:3, 3]


def _neighbour_planes(scene, view, pts_world):
    """For world points, the plane through view's back-projected pixel centres around their projection.

    Returns (distance of each point to that plane, coplanarity residual of the 4 neighbours,
    |distance to view - interpolated depth|)."""
    d = scene.depth(view.name).astype(np.float64)
    h, w = d.shape
    q = world_points(scene, view)
    pose = view.pose_matrix
    local = (pts_world - pose[:3, 3]) @ pose[:3, :3]
    phi, theta = dirs_to_angles(local)
    col, row = angles_to_pixel(phi, theta, h, w)
    c0 = np.floor(col).astype(int)
    r0 = np.clip(np.floor(row).astype(int), 0, h - 2)
    c1 = (c0 + 1) % w
    c0 = c0 % w
    q00, q01, q10, q11 = q[r0, c0], q[r0, c1], q[r0 + 1, c0], q[r0 + 1, c1]
    n = np.cross(q01 - q00, q10 - q00)
    n /= np.linalg.norm(n, axis=-1, keepdims=True) + 1e-300
    dist_plane = np.abs(np.einsum("ij,ij->i", pts_world - q00, n))
    coplanar = np.abs(np.einsum("ij,ij->i", q11 - q00, n))
    dd = np.linalg.norm(local, axis=-1)
    fr, fc = row - np.floor(row), col - np.floor(col)
    top = d[r0, c0] * (1 - fc) + d[r0, c1] * fc
    bottom = d[r0 + 1, c0] * (1 - fc) + d[r0 + 1, c1] * fc
    interp = top * (1 - fr) + bottom * fr
    return dist_plane, coplanar, np.abs(dd - interp), n


def _own_planes(scene, view):
    """Unit normal of the plane through each pixel's back-projection and its right/lower
    neighbours, and the coplanarity residual of the 2x2 block, [H-1, W]."""
    q = world_points(scene, view)
    q00, q01 = q[:-1], np.roll(q, -1, axis=1)[:-1]
    q10, q11 = q[1:], np.roll(q, -1, axis=1)[1:]
    n = np.cross(q01 - q00, q10 - q00)
    n /= np.linalg.norm(n, axis=-1, keepdims=True) + 1e-300
    return q00, n, np.abs(np.einsum("...j,...j->...", q11 - q00, n))


@pytest.mark.parametrize("preset", ["cuboid", "l-shape", "two-rooms"])
def test_two_view_backprojection_agrees(scenes, preset):
    """Depth back-projected from one view lies on the surfaces another view's depth describes:
    each point of view A (on a plane, by its own 2x2 neighbourhood) is compared with the plane
    through view B's back-projected pixel centres around its projection, where both describe
    the same plane (same normal) and B sees it (not occluded)."""
    scene = scenes[(preset, "furniture")]
    views = scene.manifest.views
    errors = []
    for va, vb in itertools.permutations(views[:3], 2):
        p, n_a, cop_a = _own_planes(scene, va)
        p, n_a, cop_a = p.reshape(-1, 3), n_a.reshape(-1, 3), cop_a.reshape(-1)
        dist, coplanar, vis, n_b = _neighbour_planes(scene, vb, p)
        same_plane = (cop_a < 1e-5) & (coplanar < 1e-5) & (np.abs(np.einsum("ij,ij->i", n_a, n_b)) > 1 - 1e-6)
        ok = same_plane & (vis < 0.05)
        assert ok.mean() > 0.1, f"too few shared points between {va.name} and {vb.name}"
        errors.append(dist[ok])
    err = np.concatenate(errors)
    assert err.mean() < 1e-3, f"mean disagreement {err.mean() * 1000:.3f} mm"
    assert np.percentile(err, 99) < 1e-5  # float32 depth: micrometres, not millimetres


@pytest.mark.parametrize("preset", PRESETS)
def test_floor_depth_matches_height_and_latitude(scenes, preset):
    """Below the floor boundary the empty room shows floor: d = h / sin(-theta)."""
    scene = scenes[(preset, "none")]
    for view in scene.manifest.views:
        d = scene.depth(view.name).astype(np.float64)
        h, w = d.shape
        _, theta = pixel_grid_angles(h, w)
        floor_bnd = scene.layout(view.name)[1].astype(np.float64)
        floor = theta < floor_bnd[None, :] - 1e-5
        assert floor.sum() > 0.2 * h * w
        expected = view.camera_height / np.sin(-theta[floor])
        np.testing.assert_allclose(d[floor], expected, rtol=1e-6)
        # The camera height in scene.json is the pose's height above the floor (y = 0, y down).
        assert view.pose_matrix[1, 3] == pytest.approx(-view.camera_height)


@pytest.mark.parametrize("preset", PRESETS)
def test_layout_boundaries_match_depth_discontinuities(scenes, preset):
    """Each column switches between floor (resp. ceiling) depth and wall depth exactly at the
    layout boundary latitude."""
    scene = scenes[(preset, "none")]
    ch = scene.ceiling_height
    for view in scene.manifest.views:
        d = scene.depth(view.name).astype(np.float64)
        h, w = d.shape
        _, theta = pixel_grid_angles(h, w)
        bnd = scene.layout(view.name).astype(np.float64)
        assert bnd.shape == (2, w)
        assert np.all(bnd[0] > 0) and np.all(bnd[1] < 0)
        hc = view.camera_height
        with np.errstate(divide="ignore"):
            is_floor = np.isclose(d, hc / np.sin(-theta), rtol=1e-5) & (theta < 0)
            is_ceiling = np.isclose(d, (ch - hc) / np.sin(theta), rtol=1e-5) & (theta > 0)
        near = 1e-5  # a pixel centre exactly on the boundary is ambiguous
        below = theta < bnd[1][None, :] - near
        above_floor = theta > bnd[1][None, :] + near
        assert np.all(is_floor[below])
        assert not np.any(is_floor[above_floor])
        up = theta > bnd[0][None, :] + near
        below_ceiling = theta < bnd[0][None, :] - near
        # Above the ceiling boundary: ceiling, or (two-rooms) the lintel over the doorway.
        lintel = np.zeros_like(is_ceiling)
        for door in scene.floor_plan["doorways"]:
            p = world_points(scene, view)
            a, b = np.asarray(door["a"]), np.asarray(door["b"])
            on_line = np.abs(p[..., 0] - a[0]) < 1e-4  # doorways lie on x = const walls
            within = (p[..., 2] >= min(a[1], b[1]) - 1e-4) & (p[..., 2] <= max(a[1], b[1]) + 1e-4)
            lintel |= on_line & within & (p[..., 1] <= door["top_y"] + 1e-4)
        assert np.all((is_ceiling | lintel)[up])
        assert not np.any(is_ceiling[below_ceiling])


@pytest.mark.parametrize("preset", PRESETS)
def test_horizonnet_json_reproduces_boundary(scenes, preset):
    scene = scenes[(preset, "none")]
    for view in scene.manifest.views:
        data = scene.layout_json(view.name)
        assert set(data) == {"z0", "z1", "uv"}
        assert data["z0"] == 50 and data["z1"] < 0
        uv = np.asarray(data["uv"])
        assert len(uv) % 2 == 0 and len(uv) >= 8
        assert np.all((uv >= 0) & (uv < 1))
        assert np.all(uv[0::2, 0] == uv[1::2, 0])  # ceiling/floor pairs share u
        assert np.all(uv[0::2, 1] < 0.5) and np.all(uv[1::2, 1] > 0.5)
        assert np.all(np.diff(uv[0::2, 0]) >= 0)  # sorted by u
        h = scene.depth(view.name).shape[0]
        rec = horizonnet_to_boundary(data, h, 2 * h)
        np.testing.assert_allclose(rec, scene.layout(view.name), atol=1e-5)
        # z1 encodes the camera height relative to the ceiling.
        ratio = -data["z1"] / data["z0"]
        assert ratio == pytest.approx(view.camera_height / (scene.ceiling_height - view.camera_height))


def test_l_shape_has_occluded_views_in_json():
    """An L-shaped room seen from one arm hides a wall: the JSON gets an occluding corner and its
    shadow point at the same u (more than 6 corners), and still reproduces the boundary."""
    from simulate.geometry import Camera, build_world
    from simulate.layout import view_layout

    world = build_world("l-shape", np.random.default_rng(3))
    xs, zs = world.outline[:, 0], world.outline[:, 1]
    # A point deep in the arm along x near z min, far from the elbow.
    p = np.array([xs.max() - 0.6, -1.5, zs.min() + 0.6])
    cam = Camera("c", "train", p, 1.5, 0.3)
    lay = view_layout(world, cam, 64)
    assert lay.representable
    uv = np.asarray(lay.horizonnet["uv"])
    us = uv[0::2, 0]
    assert np.any(np.isclose(np.diff(us), 0.0)), "expected an occlusion pair at the same u"


def test_two_rooms_doorway_boundary(scenes):
    """Through the doorway both boundaries lie on the other room's far wall (farther than the
    shared wall); the JSON (with door jambs as occluding corners) still reproduces them."""
    scene = scenes[("two-rooms", "none")]
    fp = scene.floor_plan
    door = fp["doorways"][0]
    x_shared = door["a"][0]
    saw_doorway = False
    for view in scene.manifest.views:
        bnd = scene.layout(view.name).astype(np.float64)
        hc = view.camera_height
        dist = hc / np.tan(-bnd[1])
        h, w = scene.depth(view.name).shape
        lon = ((np.arange(w) + 0.5) / w - 0.5) * 2 * np.pi
        dirs = np.stack([np.sin(lon), np.zeros(w), np.cos(lon)], -1) @ view.pose_matrix[:3, :3].T
        end_x = view.position[0] + dist * dirs[:, 0]
        own_side = np.sign(view.position[0] - x_shared)
        beyond = np.sign(end_x - x_shared) == -own_side
        saw_doorway |= bool(np.any(beyond & (np.abs(end_x - x_shared) > 0.2)))
        rec = horizonnet_to_boundary(scene.layout_json(view.name), h, w)
        np.testing.assert_allclose(rec, bnd, atol=1e-5)
        if view.split == "train":
            assert view.layout == f"layout/{view.name}.json"
    assert saw_doorway


@pytest.mark.parametrize("preset", ["cuboid", "two-rooms"])
def test_seam_is_continuous(scenes, preset):
    """Columns 0 and W-1 are neighbours: their difference is like any two adjacent columns'."""
    scene = scenes[(preset, "texture,furniture,shading,aa")]
    for view in scene.manifest.views:
        img = scene.image(view.name).astype(np.float64)
        adj = np.abs(np.diff(img, axis=1)).mean(axis=(0, 2))
        seam = np.abs(img[:, 0] - img[:, -1]).mean()
        assert seam <= adj.max() + 1.0
        assert seam <= 3 * np.median(adj) + 25.0  # no seam-sized jump
        d = scene.depth(view.name).astype(np.float64)
        rel_adj = np.median(np.abs(np.diff(d, axis=1)) / d[:, 1:], axis=0)
        rel_seam = np.median(np.abs(d[:, 0] - d[:, -1]) / d[:, 0])
        assert rel_seam <= np.percentile(rel_adj, 99) + 1e-6


def test_seam_exact_under_half_turn():
    """Turning the camera by pi rolls the panorama by W/2: the seam becomes an interior column."""
    from simulate.geometry import Camera, build_world
    from simulate.render import render_view

    world = build_world("cuboid", np.random.default_rng(0))
    cam = Camera("a", "train", np.array([0.3, -1.4, -0.2]), 1.4, 0.7)
    cam2 = Camera("b", "train", cam.position, 1.4, 0.7 + np.pi)
    fx = {"texture", "shading", "aa"}
    r1 = render_view(world, [], cam, 32, fx, 2, None, {})
    r2 = render_view(world, [], cam2, 32, fx, 2, None, {})
    np.testing.assert_allclose(r2.depth, np.roll(r1.depth, 32, axis=1), rtol=1e-9)
    np.testing.assert_allclose(r2.image, np.roll(r1.image, 32, axis=1), atol=2e-3)


def test_depth_png_is_millimetres(scenes):
    import cv2

    scene = scenes[("cuboid", "none")]
    for view in scene.manifest.views:
        png = cv2.imread(str(scene.root / "gt" / "depth" / f"{view.name}.png"), cv2.IMREAD_UNCHANGED)
        assert png.dtype == np.uint16
        np.testing.assert_allclose(png / 1000.0, scene.depth(view.name), atol=0.0005 + 1e-6)


@pytest.mark.parametrize("preset", PRESETS)
def test_union_of_view_floor_plans_is_the_room(scenes, preset):
    """Per-view floor plans from the gt layout (floor boundary + camera height), moved to the
    world by the poses and merged, give the rooms' union (what the pipeline's union stage does)."""
    from shapely.geometry import Polygon
    from shapely.ops import unary_union

    scene = scenes[(preset, "none")]
    polys = []
    for view in scene.manifest.train_views():
        bnd = scene.layout(view.name).astype(np.float64)
        w = bnd.shape[1]
        lon = ((np.arange(w) + 0.5) / w - 0.5) * 2 * np.pi
        dist = view.camera_height / np.tan(-bnd[1])
        local = np.stack([dist * np.sin(lon), np.zeros(w), dist * np.cos(lon)], -1)
        world = local @ view.pose_matrix[:3, :3].T + view.pose_matrix[:3, 3]
        polys.append(Polygon(world[:, [0, 2]]).buffer(0))
    union = unary_union(polys)
    room = Polygon(scene.floor_plan["outline"])
    iou = union.intersection(room).area / union.union(room).area
    assert iou >= 0.98, f"IoU {iou:.4f}"
