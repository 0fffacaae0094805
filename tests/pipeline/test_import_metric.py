"""import-colmap and import-nerfstudio made metric: synthetic captures come back as the truth, depth in metres."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest
from scipy.spatial.transform import Rotation

from panogeom import angles_to_dirs
from panogeom.equirect import angles_to_pixel, dirs_to_angles
from pipeline.importers import SPARSE_POINTS
from schemas.scene import REAL_CAPTURE_NADIR_DEG
from tests.clitools import invoke

HEIGHT, WIDTH = 32, 64
CAMERA_HEIGHT = 1.5  # metres over the floor y = 0 (the world is y down)


def true_poses() -> dict[str, np.ndarray]:
    """Camera-to-world poses of levelled cameras CAMERA_HEIGHT over the floor, turned about y."""
    out = {}
    for i, (x, z, yaw) in enumerate([(0.0, 0.0, 0.0), (1.2, 0.3, 40.0), (0.4, 1.5, -70.0), (-0.8, 0.9, 150.0)]):
        pose = np.eye(4)
        pose[:3, :3] = Rotation.from_euler("y", yaw, degrees=True).as_matrix()
        pose[:3, 3] = [x, -CAMERA_HEIGHT, z]
        out[f"pano{i}"] = pose
    return out


def room_points(rng: np.random.Generator) -> np.ndarray:
    """A floor (y = 0) and a wall of a room."""
    floor = np.column_stack([rng.uniform(-2, 2.5, 300), np.zeros(300), rng.uniform(-2, 2.5, 300)])
    # the wall stops short of the floor: the floor fit then sees the floor alone, exactly
    wall = np.column_stack([rng.uniform(-2, 2.5, 200), rng.uniform(-2.5, -0.3, 200), np.full(200, 3.0)])
    return np.vstack([floor, wall])


def write_model(folder: Path, poses: dict[str, np.ndarray], sfm_from_world: np.ndarray, sfm_scale: float,
                text: bool = False, model: str = "EQUIRECTANGULAR") -> Path:
    """A COLMAP model of `poses` and the room in an arbitrary SfM frame, x_sfm = s R x + t
    (`sfm_from_world` rigid holds R and t, `sfm_scale` s)."""
    rec = pycolmap.Reconstruction()
    params = [WIDTH, HEIGHT] if model == "EQUIRECTANGULAR" else [50.0, WIDTH / 2, HEIGHT / 2]
    rec.add_camera_with_trivial_rig(pycolmap.Camera(model=model, width=WIDTH, height=HEIGHT, params=params,
                                                    camera_id=1))
    rotation, offset = sfm_from_world[:3, :3], sfm_from_world[:3, 3]
    for image_id, (name, pose) in enumerate(sorted(poses.items()), start=1):
        cam_to_sfm = np.eye(4)
        cam_to_sfm[:3, :3] = rotation @ pose[:3, :3]
        cam_to_sfm[:3, 3] = sfm_scale * rotation @ pose[:3, 3] + offset
        image = pycolmap.Image(name=f"{name}.png", camera_id=1, image_id=image_id)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(np.linalg.inv(cam_to_sfm)[:3]))
    for xyz in room_points(np.random.default_rng(0)):
        rec.add_point3D(sfm_scale * rotation @ xyz + offset, pycolmap.Track(), np.array([200, 180, 160], np.uint8))
    folder.mkdir(parents=True)
    (rec.write_text if text else rec.write_binary)(str(folder))
    return folder


def sfm_frame() -> np.ndarray:
    """An arbitrary rigid SfM frame (COLMAP's world is wherever its first pair put it)."""
    m = np.eye(4)
    m[:3, :3] = Rotation.random(random_state=3).as_matrix()
    m[:3, 3] = [1.0, 2.0, 3.0]
    return m


@pytest.fixture
def capture(tmp_path):
    """(model folder, images folder) of the four true poses, SfM scale 0.37."""
    images = tmp_path / "images"
    images.mkdir()
    for name in true_poses():
        cv2.imwrite(str(images / f"{name}.png"), np.zeros((HEIGHT, WIDTH, 3), np.uint8))
    return write_model(tmp_path / "sparse" / "0", true_poses(), sfm_frame(), 0.37), images


def imported_poses(scene_json: Path) -> dict[str, np.ndarray]:
    return {v["name"]: np.array(v["pose"]) for v in json.loads(scene_json.read_text())["views"]}


def expected_poses() -> dict[str, np.ndarray]:
    """The truth in the importer's frame: the first camera (by name) at the origin; the truth's
    cameras are level and pano0 looks along +z, so only a translation remains."""
    truth = true_poses()
    shift = truth["pano0"][:3, 3].copy()
    for pose in truth.values():
        pose[:3, 3] -= shift
    return truth


def test_colmap_equirect_pixels_are_ours():
    """COLMAP's EQUIRECTANGULAR camera maps a camera-frame direction to the pixel DESIGN.md does
    (COLMAP's pixel centres sit at +0.5, ours at integers): its camera frame is ours unchanged."""
    camera = pycolmap.Camera(model="EQUIRECTANGULAR", width=WIDTH, height=HEIGHT, params=[WIDTH, HEIGHT])
    rng = np.random.default_rng(4)
    dirs = angles_to_dirs(rng.uniform(-3.1, 3.1, 50), rng.uniform(-1.5, 1.5, 50))
    col, row = angles_to_pixel(*dirs_to_angles(dirs), HEIGHT, WIDTH)
    np.testing.assert_allclose(np.asarray(camera.img_from_cam(dirs)) - 0.5, np.column_stack([col, row]), atol=1e-9)


@pytest.mark.parametrize("text", [False, True], ids=["binary", "text"])
def test_round_trip_camera_height(capture, tmp_path, capsys, text):
    model, images = capture
    if text:
        model = write_model(tmp_path / "text", true_poses(), sfm_frame(), 0.37, text=True)
    code, out, err = invoke(["import-colmap", model, images, tmp_path / "scene", "--camera-height", "1.5"], capsys)
    assert code == 0, err
    got, want = imported_poses(tmp_path / "scene" / "scene.json"), expected_poses()
    assert got.keys() == want.keys()
    for name in want:
        np.testing.assert_allclose(got[name], want[name], atol=1e-6)
    manifest = json.loads((tmp_path / "scene" / "scene.json").read_text())
    assert manifest["nadir_mask_deg"] == REAL_CAPTURE_NADIR_DEG
    assert [v["split"] for v in manifest["views"]] == ["train"] * 4
    np.testing.assert_allclose([v["camera_height"] for v in manifest["views"]], 1.5, atol=1e-9)
    assert (tmp_path / "scene" / "images" / "pano2.png").is_file() and (tmp_path / "scene" / SPARSE_POINTS).is_file()


def test_scale_and_options(capture, tmp_path, capsys):
    model, images = capture
    code, _, err = invoke(["import-colmap", model, images, tmp_path / "scene", "--scale", str(1 / 0.37),
                           "--test-every", "2", "--nadir-mask-deg", "0"], capsys)
    assert code == 0, err
    got, want = imported_poses(tmp_path / "scene" / "scene.json"), expected_poses()
    for name in want:
        np.testing.assert_allclose(got[name], want[name], atol=1e-6)
    manifest = json.loads((tmp_path / "scene" / "scene.json").read_text())
    assert [v["split"] for v in manifest["views"]] == ["train", "test"] * 2
    assert manifest["nadir_mask_deg"] == 0
    # the floor is still found, so the heights are measured: 1.5 m at this scale
    np.testing.assert_allclose([v["camera_height"] for v in manifest["views"]], 1.5, atol=1e-9)


def test_no_height_assumes_the_default(capture, tmp_path, capsys):
    model, images = capture
    code, out, _ = invoke(["import-colmap", model, images, tmp_path / "scene"], capsys)
    assert code == 0 and "assumes cameras 1.6 m over the floor" in out
    got = imported_poses(tmp_path / "scene" / "scene.json")
    np.testing.assert_allclose(got["pano1"][:3, 3], expected_poses()["pano1"][:3, 3] * 1.6 / 1.5, atol=1e-6)


def one_error_line(err: str) -> str:
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    return lines[0]


def test_bad_inputs_exit_2_with_one_line(capture, tmp_path, capsys):
    model, images = capture
    perspective = write_model(tmp_path / "persp", true_poses(), sfm_frame(), 1.0, model="SIMPLE_PINHOLE")
    (images / "pano3.png").rename(tmp_path / "moved.png")
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "keep.txt").write_text("mine")
    (tmp_path / "empty_model").mkdir()
    cases = [
        ([tmp_path / "nope", images], "nope: COLMAP model folder does not exist"),
        ([tmp_path / "empty_model", images], "cameras.bin: missing (neither .bin nor .txt)"),
        ([perspective, images], "camera 1 is SIMPLE_PINHOLE: only EQUIRECTANGULAR cameras are supported"),
        ([model, tmp_path / "no_images"], "no_images: images folder does not exist"),
        ([model, images], "pano3.png: image missing (named by the COLMAP model)"),
    ]
    for args, message in cases:
        code, _, err = invoke(["import-colmap", *args, tmp_path / "out"], capsys)
        assert code == 2 and message in one_error_line(err), (message, err)
        assert not (tmp_path / "out").exists()
    (tmp_path / "moved.png").rename(images / "pano3.png")
    code, _, err = invoke(["import-colmap", model, images, tmp_path / "full", "--scale", "2"], capsys)
    assert code == 2 and "exists and is not empty" in one_error_line(err)
    assert [p.name for p in (tmp_path / "full").iterdir()] == ["keep.txt"]
    code, _, err = invoke(["import-colmap", model, images, tmp_path / "o", "--scale", "2", "--camera-height", "1"],
                          capsys)
    assert code == 2 and "--camera-height or --scale, not both" in one_error_line(err)


# -- nerfstudio: depth files and metric scale ---------------------------------------------------

#: nerfstudio units per metre in the synthetic transforms.json (poses and depth alike)
UNITS_PER_METRE = 2.0


def floor_depth(pose: np.ndarray) -> np.ndarray:
    """[H,W] distance along each ray (metres) to the floor y = 0 and the ceiling y = -2.5."""
    dirs = angles_to_dirs(*np.meshgrid(((np.arange(WIDTH) + 0.5) / WIDTH - 0.5) * 2 * np.pi,
                                       (0.5 - (np.arange(HEIGHT) + 0.5) / HEIGHT) * np.pi)) @ pose[:3, :3].T
    y0, dy = pose[1, 3], dirs[..., 1]
    plane = np.where(dy > 0, 0.0, -2.5)
    with np.errstate(divide="ignore"):
        t = (plane - y0) / dy
    return np.where(np.abs(dy) > 1e-3, t, 0.0)


def write_transforms(folder: Path, depth_format: str | None) -> Path:
    """transforms.json of the true poses in nerfstudio units, with depth files in `depth_format`:
    'png' (uint16 milli-units, nerfstudio's default depth_unit_scale_factor) or 'npy' (units)."""
    from pipeline.importers import pose_to_nerfstudio

    (folder / "images").mkdir(parents=True)
    (folder / "depths").mkdir()
    frames = []
    for name, pose in true_poses().items():
        cv2.imwrite(str(folder / "images" / f"{name}.png"), np.zeros((HEIGHT, WIDTH, 3), np.uint8))
        scaled = pose.copy()
        scaled[:3, 3] *= UNITS_PER_METRE
        frame = {"file_path": f"images/{name}.png", "transform_matrix": pose_to_nerfstudio(scaled).tolist()}
        units = floor_depth(pose) * UNITS_PER_METRE
        if depth_format == "png":
            frame["depth_file_path"] = f"depths/{name}.png"
            cv2.imwrite(str(folder / frame["depth_file_path"]), np.round(units * 1000).astype(np.uint16))
        elif depth_format == "npy":
            frame["depth_file_path"] = f"depths/{name}.npy"
            np.save(folder / frame["depth_file_path"], units.astype(np.float64))
        frames.append(frame)
    meta = {"camera_model": "EQUIRECTANGULAR", "frames": frames}
    if depth_format == "npy":
        meta["depth_unit_scale_factor"] = 1.0
    (folder / "transforms.json").write_text(json.dumps(meta))
    return folder / "transforms.json"


def test_nerfstudio_keeps_depth_in_metres(tmp_path, capsys):
    transforms = write_transforms(tmp_path / "ns", "png")
    code, _, err = invoke(["import-nerfstudio", transforms, tmp_path / "scene", "--scale", "0.5",
                           "--test-every", "0"], capsys)
    assert code == 0, err
    manifest = json.loads((tmp_path / "scene" / "scene.json").read_text())
    assert manifest["nadir_mask_deg"] == REAL_CAPTURE_NADIR_DEG
    for view in manifest["views"]:
        pose = true_poses()[view["name"]]
        np.testing.assert_allclose(view["pose"], pose, atol=1e-9)  # --scale 0.5 undoes 2 units per metre
        assert view["depth"] == f"depth/{view['name']}.npy"
        depth = np.load(tmp_path / "scene" / view["depth"])
        truth = floor_depth(pose)
        # PNG milli-units, rounded: half a milli-unit is a quarter of a millimetre
        np.testing.assert_allclose(depth[truth > 0], truth[truth > 0], atol=2.6e-4)
        assert np.all(depth[truth == 0] == 0)


def test_nerfstudio_camera_height_from_the_depth_floor(tmp_path, capsys):
    transforms = write_transforms(tmp_path / "ns", "npy")
    code, _, err = invoke(["import-nerfstudio", transforms, tmp_path / "scene", "--camera-height", "1.5"], capsys)
    assert code == 0, err
    manifest = json.loads((tmp_path / "scene" / "scene.json").read_text())
    for view in manifest["views"]:
        np.testing.assert_allclose(view["pose"], true_poses()[view["name"]], atol=1e-6)
        assert view["camera_height"] == pytest.approx(1.5, abs=1e-6)
        truth = floor_depth(true_poses()[view["name"]])
        np.testing.assert_allclose(np.load(tmp_path / "scene" / view["depth"]), truth, atol=1e-6)


def test_nerfstudio_camera_height_without_depth_is_refused(tmp_path, capsys):
    transforms = write_transforms(tmp_path / "ns", None)
    code, _, err = invoke(["import-nerfstudio", transforms, tmp_path / "scene", "--camera-height", "1.5"], capsys)
    assert code == 2
    assert "--camera-height needs every frame's depth_file_path" in one_error_line(err)
    assert not (tmp_path / "scene").exists()


def test_status_says_which_views_lack_a_pose(capture, tmp_path, capsys):
    """An imported scene has every pose (poses skipped); with two left out, status says why it runs."""
    from pipeline.engine import Engine
    from pipeline.registry import build_registry
    from schemas.scene_loader import load_scene

    model, images = capture
    assert invoke(["import-colmap", model, images, tmp_path / "scene", "--scale", "1"], capsys)[0] == 0
    plan = Engine(load_scene(tmp_path / "scene"), tmp_path / "run", build_registry()).plan()["poses"]
    assert (plan.state, plan.reason) == ("skipped", "every view has a pose in scene.json")
    scene_json = tmp_path / "scene" / "scene.json"
    manifest = json.loads(scene_json.read_text())
    for view in manifest["views"][1:3]:
        del view["pose"]
    scene_json.write_text(json.dumps(manifest))
    plan = Engine(load_scene(tmp_path / "scene"), tmp_path / "run", build_registry()).plan()["poses"]
    assert (plan.state, plan.reason) == ("missing", "never run; 2 of 4 views have no pose in scene.json")
