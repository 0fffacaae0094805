"""Boundaries → metric room, against analytic rooms (exact shapely ray casting)."""

from __future__ import annotations

import numpy as np
import pytest
from layout_helpers import CUBOID, L_SHAPE, exact_boundaries, match_corners, world_to_camera_xz
from shapely.geometry import Point, Polygon

from layoutnet import postprocess as pp

H_CAM, H_ROOM = 1.5, 2.8  # camera height, floor-to-ceiling (m)
PENTAGON = [(-2.0, -1.5), (2.5, -1.5), (2.5, 0.5), (0.5, 2.4), (-2.0, 2.4)]  # one wall at 43.5 degrees


def _corner_signal(true_cam_xz: np.ndarray, width: int) -> np.ndarray:
    """HorizonNet-like corner probabilities: 0.96^distance (columns) to the nearest corner."""
    phi = np.arctan2(true_cam_xz[:, 0], true_cam_xz[:, 1])
    col = (phi / (2 * np.pi) + 0.5) * width - 0.5
    c = np.arange(width)[:, None]
    d = np.abs(c - col[None])
    d = np.minimum(d, width - d).min(axis=1)
    return 0.96**d


@pytest.mark.parametrize(
    "poly,cam,yaw",
    [
        (CUBOID, (0.1, 0.2), 0.0),
        (CUBOID, (-0.6, 0.9), 0.7),
        (L_SHAPE, (0.1, 0.2), 0.3),
        (L_SHAPE, (-0.5, 0.5), -1.2),
    ],
)
@pytest.mark.parametrize("mode", ["manhattan", "atlanta"])
@pytest.mark.parametrize("width", [1024, 256])
def test_exact_boundaries_give_exact_room(poly, cam, yaw, mode, width):
    b = exact_boundaries(poly, cam, H_CAM, H_ROOM, width, yaw)
    room = pp.layout_from_boundaries(b, H_CAM, mode=mode)
    true = world_to_camera_xz(poly, cam, yaw)
    assert room.method == mode and room.notes == []
    assert len(room.polygon) == len(true)
    assert match_corners(room.polygon, true) < 0.01
    assert abs(room.ceiling_distance - (H_ROOM - H_CAM)) < 0.01
    assert Polygon(room.polygon).exterior.is_ccw


def test_exact_boundaries_cuboid_mode_and_corner_signal():
    b = exact_boundaries(CUBOID, (0.3, -0.4), H_CAM, H_ROOM, 512, 0.4)
    true = world_to_camera_xz(CUBOID, (0.3, -0.4), 0.4)
    for cor in (None, _corner_signal(true, 1024)):  # cor at the model's width, boundaries at another
        room = pp.layout_from_boundaries(b, H_CAM, cor=cor, mode="cuboid")
        assert room.method == "cuboid" and len(room.polygon) == 4
        assert match_corners(room.polygon, true) < 0.01


@pytest.mark.parametrize(
    "poly,cam,yaw", [(CUBOID, (0.1, 0.2), 0.0), (L_SHAPE, (0.1, 0.2), 0.3), (L_SHAPE, (-0.5, 0.5), -0.7)]
)
@pytest.mark.parametrize("with_cor", [False, True])
def test_one_pixel_noise_within_5cm(poly, cam, yaw, with_cor):
    """Gaussian noise of one pixel (sigma) on both boundaries of a 512x1024 panorama."""
    width = 1024
    b = exact_boundaries(poly, cam, H_CAM, H_ROOM, width, yaw)
    true = world_to_camera_xz(poly, cam, yaw)
    px = np.pi / (width // 2)
    for seed in range(4):
        noisy = b + np.random.default_rng(seed).normal(0.0, px, b.shape)
        cor = _corner_signal(true, width) if with_cor else None
        room = pp.layout_from_boundaries(noisy, H_CAM, cor=cor)
        assert len(room.polygon) == len(true), (seed, room.method)
        assert match_corners(room.polygon, true) < 0.05, seed
        assert abs(room.ceiling_distance - (H_ROOM - H_CAM)) < 0.05


def test_atlanta_keeps_oblique_walls_manhattan_does_not():
    cam = (0.0, 0.3)
    b = exact_boundaries(PENTAGON, cam, H_CAM, H_ROOM, 1024, 0.2)
    true = world_to_camera_xz(PENTAGON, cam, 0.2)
    at = pp.layout_from_boundaries(b, H_CAM, mode="atlanta")
    assert len(at.polygon) == 5 and match_corners(at.polygon, true) < 0.01
    mh = pp.layout_from_boundaries(b, H_CAM, mode="manhattan")
    # Manhattan walls cannot follow the 43.5-degree wall: a staircase or a box, never the pentagon.
    assert len(mh.polygon) != 5 or match_corners(mh.polygon, true) > 0.1
    assert Polygon(mh.polygon).is_valid and Polygon(mh.polygon).contains(Point(0, 0))


def test_occluded_view_reproduces_the_visible_boundaries():
    """From (2, -0.5) the L's far arm hides behind its inner corner: the fitted room must
    be the visible one (a hidden connecting wall on the corner's ray)."""
    width = 1024
    b = exact_boundaries(L_SHAPE, (2.0, -0.5), H_CAM, H_ROOM, width, 0.3)
    room = pp.layout_from_boundaries(b, H_CAM)
    assert room.method == "manhattan"
    fit = pp.polygon_to_boundaries(room.polygon, room.camera_height, room.ceiling_distance, width)
    err = np.abs(fit - b).max(axis=0)
    assert np.median(err) < 1e-9
    assert (err > 1e-3).sum() <= 2  # at most the column(s) at the occluding edge


def test_polygon_to_boundaries_matches_shapely_ray_casting():
    true = world_to_camera_xz(L_SHAPE, (0.4, -0.3), 0.9)
    ref = exact_boundaries(L_SHAPE, (0.4, -0.3), H_CAM, H_ROOM, 300, 0.9)
    got = pp.polygon_to_boundaries(true, H_CAM, H_ROOM - H_CAM, 300)
    np.testing.assert_allclose(got, ref, atol=1e-9)


def test_estimate_ceiling_distance_is_robust_to_outliers():
    b = exact_boundaries(CUBOID, (0.1, 0.2), H_CAM, H_ROOM, 512, 0.0)
    b[0, :40] = 1.2  # a lamp hides part of the ceiling boundary
    assert abs(pp.estimate_ceiling_distance(b, H_CAM) - (H_ROOM - H_CAM)) < 1e-9


def test_find_peaks_circular_wraps_and_suppresses():
    w = 200
    s = np.zeros(w)
    s[[0, 2, 50, 120, 199]] = [0.9, 0.5, 0.8, 0.04, 0.95]
    pk = pp.find_peaks_circular(s, r=0.05, min_v=0.05)  # window 5 columns, wraps at the seam
    assert pk.tolist() == [50, 199]
    assert pp.find_peaks_circular(s, r=0.05, min_v=0.0, n=1).tolist() == [199]
    s2 = np.zeros(w)
    s2[10:13] = 0.7  # a flat top counts once
    assert pp.find_peaks_circular(s2, r=0.05, min_v=0.05).tolist() == [10]


def test_garbage_boundaries_fall_back_to_a_valid_room():
    rng = np.random.default_rng(3)
    b = np.stack([rng.uniform(0.05, 1.4, 256), -rng.uniform(0.05, 1.4, 256)])
    room = pp.layout_from_boundaries(b, 1.6, cor=rng.uniform(0, 1, 1024))
    poly = Polygon(room.polygon)
    assert poly.is_valid and poly.contains(Point(0, 0)) and poly.exterior.is_ccw
    assert room.method in {"manhattan", "cuboid", "raw"}


def test_flat_boundaries_circle_room_is_handled():
    """An untrained HorizonNet outputs nearly flat boundaries: a round room, no corners."""
    b = np.stack([np.full(1024, 0.478), np.full(1024, -0.425)])
    for mode in ("manhattan", "cuboid", "atlanta"):
        room = pp.layout_from_boundaries(b, 1.6, cor=np.full(1024, 0.27), mode=mode)
        poly = Polygon(room.polygon)
        assert poly.is_valid and poly.contains(Point(0, 0))
        assert room.ceiling_distance == pytest.approx(1.6 * np.tan(0.478) / np.tan(0.425))


def test_check_boundaries_rejects_bad_shapes():
    with pytest.raises(ValueError, match=r"\[2,W\]"):
        pp.layout_from_boundaries(np.zeros((3, 64)), 1.6)
    with pytest.raises(ValueError, match="NaN"):
        pp.layout_from_boundaries(np.full((2, 64), np.nan), 1.6)
