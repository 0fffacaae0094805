"""Manhattan alignment (layoutnet.alignment) and its use by the layout stage: known rotations of
simulated and real panoramas are recovered, and a turned panorama gives the same room."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import torch.nn as nn
from layout_helpers import run_layout
from scipy.spatial.transform import Rotation

from layoutnet.alignment import boundaries_to_view, estimate_alignment
from panogeom.equirect import ray_directions
from panogeom.rotate import rotate_equirect, yaw_matrix, yaw_tilt_deg

DEMO = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "horizonnet_demo" / "demo_aligned_rgb.png"


def _rotation(yaw_deg: float, tilt_deg: float, tilt_azimuth_deg: float) -> np.ndarray:
    """Camera-to-room rotation: tilted by `tilt_deg` about a horizontal axis, then turned by yaw."""
    az = np.radians(tilt_azimuth_deg)
    tilt = Rotation.from_rotvec(np.radians(tilt_deg) * np.array([np.cos(az), 0.0, np.sin(az)])).as_matrix()
    return yaw_matrix(np.radians(yaw_deg)) @ tilt


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(Rotation.from_matrix(a @ b.T).magnitude()))


# (yaw, tilt, direction of the tilt), degrees: yaw within the ±45° the alignment chooses among
ROTATIONS = [(20.0, 5.0, 30.0), (-35.0, 10.0, 120.0), (8.0, 2.0, 250.0), (41.0, 7.5, -60.0)]


@pytest.fixture(scope="module")
def simulated() -> np.ndarray:
    """A textured room from the simulator, camera level and square to the walls."""
    pytest.importorskip("simulate")
    from simulate.geometry import Camera, build_world
    from simulate.render import render_view

    rng = np.random.default_rng(0)
    world = build_world("cuboid", rng)
    x0, z0, x1, z1 = world.camera_regions[0][0]
    cam = Camera("v", "train", np.array([0.4 * x0 + 0.6 * x1, -1.5, 0.55 * z0 + 0.45 * z1]), 1.5, 0.0)
    return render_view(world, [], cam, 512, {"texture"}, 1, rng, {}).image.astype(np.float32)


@pytest.mark.parametrize("yaw,tilt,azimuth", ROTATIONS)
def test_recovers_known_rotations_of_a_simulated_panorama(simulated, yaw, tilt, azimuth):
    M = _rotation(yaw, tilt, azimuth)
    view = rotate_equirect(simulated, M.T)  # what a camera turned by M sees
    found = estimate_alignment(view)
    assert found.gravity == "lines" and found.inliers > 50
    assert _angle_deg(found.rotation, M) < 0.5
    y, t = yaw_tilt_deg(found.rotation)
    assert abs(y - yaw) < 0.5 and abs(t - tilt) < 0.5
    # gravity given (a pose): only the yaw is estimated
    given = estimate_alignment(view, down=M.T @ np.array([0.0, 1.0, 0.0]))
    assert given.gravity == "pose" and _angle_deg(given.rotation, M) < 0.5


def test_an_aligned_panorama_stays_as_it_is(simulated):
    found = estimate_alignment(simulated)
    assert _angle_deg(found.rotation, np.eye(3)) < 0.2


@pytest.mark.skipif(not DEMO.is_file(), reason="shared demo data absent")
@pytest.mark.parametrize("yaw,tilt,azimuth", [(20.0, 5.0, 30.0), (-30.0, 8.0, 100.0), (12.0, 10.0, 200.0)])
def test_recovers_known_rotations_of_the_horizonnet_demo(yaw, tilt, azimuth):
    """A real panorama (PanoContext, aligned by HorizonNet's preprocess.py), turned by a known amount."""
    from panogeom.images import read_rgb

    demo = read_rgb(DEMO)
    M = _rotation(yaw, tilt, azimuth)
    found = estimate_alignment(rotate_equirect(demo, M.T))
    assert _angle_deg(found.rotation, M) < 1.0


def test_too_few_lines_leaves_the_panorama_as_it_is():
    flat = np.full((128, 256, 3), 0.5, dtype=np.float32)
    found = estimate_alignment(flat)
    assert found.gravity == "none" and np.allclose(found.rotation, np.eye(3)) and found.notes
    down = np.array([0.0, np.cos(0.1), np.sin(0.1)])
    levelled = estimate_alignment(flat, down=down)  # the pose's gravity still levels it
    assert np.allclose(levelled.rotation @ down, [0.0, 1.0, 0.0])


def test_rotate_equirect_whole_pixel_yaw_is_a_roll_and_boundaries_follow():
    rng = np.random.default_rng(0)
    img = rng.random((32, 64, 3)).astype(np.float32)
    R = yaw_matrix(2 * np.pi * 5 / 64)  # five columns
    assert np.allclose(rotate_equirect(img, R), np.roll(img, 5, axis=1), atol=1e-5)
    bounds = np.stack([0.3 + 0.1 * np.sin(np.linspace(0, 2 * np.pi, 64, endpoint=False)),
                       -0.5 + 0.05 * np.cos(np.linspace(0, 4 * np.pi, 64, endpoint=False))])
    # boundaries found in the turned (aligned) image, seen from the original view: rolled back
    back, _ = boundaries_to_view(bounds, R, 64)
    assert np.allclose(back, np.roll(bounds, -5, axis=1), atol=1e-9)


# ----------------------------------------------------------------------------- through the stage
ROOM = {"x": (-2.0, 3.0), "z": (-1.5, 2.5), "camera_height": 1.5, "ceiling_distance": 1.3}


def _render_room(rotation: np.ndarray, height: int = 512, ss: int = 2) -> np.ndarray:
    """A box room seen by a camera at the origin with camera-to-room `rotation`: bright ceiling,
    mid-grey walls (two tones), dark floor, a door; 2x2 supersampled."""
    (x0, x1), (z0, z1) = ROOM["x"], ROOM["z"]
    h, c = ROOM["camera_height"], ROOM["ceiling_distance"]
    d = ray_directions(height * ss, 2 * height * ss) @ rotation.T  # room-frame directions
    with np.errstate(divide="ignore", invalid="ignore"):
        t_wall_x = np.where(d[..., 0] > 0, x1, x0) / d[..., 0]
        t_wall_z = np.where(d[..., 2] > 0, z1, z0) / d[..., 2]
        t_plane = np.where(d[..., 1] > 0, h, -c) / d[..., 1]
    t = np.stack([np.abs(t_wall_x), np.abs(t_wall_z), np.abs(t_plane)], -1)
    hit = np.argmin(np.nan_to_num(t, nan=np.inf, posinf=np.inf), axis=-1)
    p = d * np.take_along_axis(t, hit[..., None], -1)
    img = np.where(hit == 0, 0.5, 0.62)
    img = np.where(hit == 2, np.where(d[..., 1] > 0, 0.12, 0.92), img)
    door = (hit == 1) & (d[..., 2] > 0) & (p[..., 0] > 0.2) & (p[..., 0] < 1.1) & (p[..., 1] > h - 2.0)
    img = np.where(door, 0.42, img).astype(np.float32)
    img = cv2.resize(img, (2 * height, height), interpolation=cv2.INTER_AREA)
    return np.repeat(img[..., None], 3, axis=2)


class StrongestEdges(nn.Module):
    """A layout 'model' that reads the image: per column, the row of the strongest vertical step
    of brightness in the upper half (ceiling boundary) and in the lower half (floor boundary).
    Only right on an aligned panorama of a box room."""

    def forward(self, x):
        g = x.mean(dim=1, keepdim=True)  # [1,1,512,1024]
        step = (g[:, :, 1:] - g[:, :, :-1]).abs()[:, 0]  # [1,511,1024]; step r lies at row r + 1
        half = 256
        upper = torch.argmax(step[:, : half - 1], dim=1).float() + 1.0
        lower = torch.argmax(step[:, half:], dim=1).float() + 1.0 + half
        lat = lambda edge: (0.5 - edge / 512.0) * torch.pi  # noqa: E731
        bon = torch.stack([-lat(upper), -lat(lower)], dim=1)  # HorizonNet measures downward
        return bon, torch.zeros(1, 1, 1024) + g.mean() * 0.0


@pytest.fixture(scope="module")
def edges_onnx(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("edges") / "edges.onnx"
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(StrongestEdges(), (torch.rand(1, 3, 512, 1024),), str(path), dynamo=False,
                          opset_version=17, input_names=["x"], output_names=["bon", "cor"])
    return path


def _scene(root: Path, rotation: np.ndarray, pose_rotation: np.ndarray) -> Path:
    (root / "images").mkdir(parents=True)
    img = _render_room(rotation)
    cv2.imwrite(str(root / "images" / "v.png"), (img[..., ::-1] * 255 + 0.5).astype(np.uint8))
    pose = np.eye(4)
    pose[:3, :3] = pose_rotation
    pose[1, 3] = -ROOM["camera_height"]
    (root / "scene.json").write_text(json.dumps({"views": [
        {"name": "v", "image": "images/v.png", "pose": pose.tolist(), "split": "train",
         "camera_height": ROOM["camera_height"]}]}))
    return root


def _corner_error(polygon, rotation: np.ndarray) -> float:
    """Largest distance from a true floor corner (in the view's frame) to the nearest fitted one,
    over the room's size."""
    (x0, x1), (z0, z1) = ROOM["x"], ROOM["z"]
    h = ROOM["camera_height"]
    room = np.array([[x0, h, z0], [x1, h, z0], [x1, h, z1], [x0, h, z1]])
    truth = (room @ rotation)[:, [0, 2]]  # Rᵀ p: the corners in the camera's frame
    fitted = np.asarray(polygon)
    size = np.hypot(x1 - x0, z1 - z0)
    return float(np.linalg.norm(truth[:, None] - fitted[None], axis=2).min(axis=1).max() / size)


@pytest.mark.parametrize("align", ["auto", "lines"])
def test_a_turned_panorama_gives_the_same_room_through_the_stage(tmp_path, edges_onnx, align):
    """20° yaw + 5° tilt: with alignment the room is the aligned one's (corners within 2 % of the
    room's size); without, the edge model reads the turned image wrongly."""
    M = _rotation(20.0, 5.0, 30.0)
    level = _scene(tmp_path / "level", np.eye(3), np.eye(3))
    turned = _scene(tmp_path / "turned", M, M)  # the pose says how the camera is turned
    ref, _ = run_layout(level, tmp_path / "out-level", model=edges_onnx, align=align)
    got, _ = run_layout(turned, tmp_path / "out-turned", model=edges_onnx, align=align)
    assert _corner_error(ref.view("v").floor_polygon, np.eye(3)) < 0.02
    lay = got.view("v")
    assert lay.alignment is not None and lay.alignment.gravity == ("pose" if align == "auto" else "lines")
    assert abs(lay.alignment.yaw_deg - 20.0) < 0.5 and abs(lay.alignment.tilt_deg - 5.0) < 0.5
    assert _corner_error(lay.floor_polygon, M) < 0.02
    assert abs(lay.camera_height + lay.ceiling_distance - 2.8) < 0.02 * 2.8
    # the boundaries are the view's own: they sit on the brightness steps of the turned image
    img = cv2.cvtColor(cv2.imread(str(turned / "images" / "v.png")), cv2.COLOR_BGR2GRAY).astype(np.float64)
    bounds = np.load(tmp_path / "out-turned" / lay.boundaries)
    rows = (0.5 - bounds / np.pi) * 512  # the edge between two rows, as a continuous row
    step = np.abs(np.diff(img, axis=0))
    cols = np.arange(1024)
    for r in rows:
        near = np.clip(np.round(r).astype(int) - 1 + np.arange(-2, 3)[:, None], 0, 510)
        assert np.median(step[near, cols].max(axis=0)) > 40  # a strong step within 2 rows


def test_without_alignment_the_turned_panorama_gives_a_wrong_room(tmp_path, edges_onnx):
    M = _rotation(20.0, 5.0, 30.0)
    turned = _scene(tmp_path / "turned", M, M)
    got, _ = run_layout(turned, tmp_path / "out", model=edges_onnx, align="off")
    assert got.view("v").alignment is None
    assert _corner_error(got.view("v").floor_polygon, M) > 0.03  # with alignment: < 0.02 (above)
