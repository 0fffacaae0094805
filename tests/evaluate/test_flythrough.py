"""Fly-through video: H.264 output, walk-direction camera paths, nerfstudio camera_path.json,
never overwriting an earlier video."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import typer
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from evaluation.flythrough import (
    catmull_rom,
    output_path,
    read_camera_path,
    walk_poses,
    write_video,
)
from runfs.errors import PanoError
from pipeline.importers import pose_to_nerfstudio

imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg")


def _pose(yaw_deg, pos):
    m = np.eye(4)
    m[:3, :3] = Rotation.from_euler("y", yaw_deg, degrees=True).as_matrix()
    m[:3, 3] = pos
    return m


def _probe(path):
    gen = imageio_ffmpeg.read_frames(str(path))
    meta = next(gen)
    frames = [np.frombuffer(f, np.uint8).reshape(meta["size"][1], meta["size"][0], 3) for f in gen]
    return meta, frames


# --- video ---------------------------------------------------------------------------------

def test_h264_video_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:24, 0:40] / 40.0
    frames = [np.stack([xx, yy, np.full_like(xx, i / 5)], -1) + 0.02 * rng.standard_normal((24, 40, 3))
              for i in range(5)]
    n = write_video(frames, tmp_path / "v.mp4", fps=10)
    meta, got = _probe(tmp_path / "v.mp4")
    assert n == 5 and meta["codec"] == "h264" and meta["pix_fmt"].startswith("yuv420p")
    assert meta["size"] == (40, 24) and meta["fps"] == 10 and len(got) == 5
    for a, b in zip(frames, got):
        assert np.abs(np.clip(a, 0, 1) * 255 - b).mean() < 6  # lossy, but close
    assert not list(tmp_path.glob(".tmp-*"))
    # odd sizes are padded to even ones (yuv420p needs them)
    write_video([np.zeros((7, 9, 3))], tmp_path / "odd.mp4")
    assert _probe(tmp_path / "odd.mp4")[0]["size"] == (10, 8)


def test_failed_write_leaves_nothing(tmp_path):
    def frames():
        yield np.zeros((8, 8, 3))
        raise RuntimeError("renderer died")

    with pytest.raises(RuntimeError):
        write_video(frames(), tmp_path / "v.mp4")
    assert list(tmp_path.iterdir()) == []


def test_output_names_never_overwrite(tmp_path):
    first = output_path(tmp_path, "train", "pano")
    assert first.name == "flythrough-train-pano.mp4"
    first.write_bytes(b"x")
    second = output_path(tmp_path, "train", "pano")
    assert second.name == "flythrough-train-pano-2.mp4"
    second.write_bytes(b"x")
    assert output_path(tmp_path, "train", "pano").name == "flythrough-train-pano-3.mp4"
    assert output_path(tmp_path, "train", "pano", overwrite=True) == first
    assert output_path(tmp_path, str(tmp_path / "my path.json"), "persp").name == "flythrough-my_path-persp.mp4"


# --- walk paths ------------------------------------------------------------------------------

def _check_walk(poses, max_deg):
    pos = poses[:, :3, 3]
    for k in range(1, len(poses) - 1):
        r = poses[k, :3, :3]
        np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-9)
        assert np.linalg.det(r) == pytest.approx(1.0)
        np.testing.assert_allclose(r[:, 1], [0, 1, 0], atol=1e-12)  # level: camera y = gravity
        motion = pos[k + 1] - pos[k - 1]
        motion[1] = 0.0
        cosang = r[:, 2] @ motion / np.linalg.norm(motion)
        assert math.degrees(math.acos(min(1.0, cosang))) < max_deg, k


def test_walk_looks_along_motion():
    # an L-shaped walk through four views whose own yaws look anywhere (mostly at walls)
    keys = [_pose(170, [0, -1.5, 0]), _pose(-60, [2, -1.4, 0]), _pose(10, [3, -1.5, 1]), _pose(95, [3, -1.5, 3])]
    out = walk_poses(keys, 80)
    assert out.shape == (80, 4, 4)
    np.testing.assert_allclose(out[0, :3, 3], keys[0][:3, 3], atol=1e-9)
    np.testing.assert_allclose(out[-1, :3, 3], keys[-1][:3, 3], atol=1e-9)
    _check_walk(out, max_deg=6)
    # steady pace: equal steps along the curve
    steps = np.linalg.norm(np.diff(out[:, :3, 3], axis=0), axis=1)
    assert steps.max() / steps.min() < 1.1
    # smooth: no frame turns by much more than its neighbours
    yaw = np.unwrap(np.arctan2(out[:, 0, 2], out[:, 2, 2]))
    assert np.abs(np.diff(yaw)).max() < math.radians(10)
    # the first frame looks from view 0 towards view 1 (+x), the last from view 2 to view 3 (+z)
    assert out[0, :3, 2] @ [1, 0, 0] > 0.95 and out[-1, :3, 2] @ [0, 0, 1] > 0.95


def test_walk_two_views_straight_and_standstill():
    out = walk_poses([_pose(0, [0, -1.5, 0]), _pose(0, [0, -1.5, 0]), _pose(0, [-2, -1.5, 0])], 9)
    np.testing.assert_allclose(out[:, :3, 2], np.tile([-1, 0, 0], (9, 1)), atol=1e-9)  # looks along -x
    np.testing.assert_allclose(out[:, 2, 3], 0, atol=1e-12)
    # a purely vertical step has no walk direction: keep a level spin in place
    spin = walk_poses([_pose(30, [1, -1.5, 0]), _pose(30, [1, -1.0, 0])], 4)
    np.testing.assert_allclose(spin[:, :3, 1], np.tile([0, 1, 0], (4, 1)), atol=1e-12)
    yaws = np.unwrap(np.arctan2(spin[:, 0, 2], spin[:, 2, 2]))
    np.testing.assert_allclose(np.diff(yaws), math.pi / 2, atol=1e-9)
    one = walk_poses([_pose(30, [1, -1.5, 0])], 4)
    assert np.all(np.isfinite(one)) and one[0, :3, 2] @ _pose(30, [0, 0, 0])[:3, 2] == pytest.approx(1)


def test_catmull_rom_passes_through_points():
    pts = np.array([[0, 0, 0], [1, 0, 0], [1, 0, 2], [3, 1, 2.0]])
    np.testing.assert_allclose(catmull_rom(pts, np.arange(4.0)), pts, atol=1e-9)


# --- nerfstudio camera paths ------------------------------------------------------------------

def _camera_path(poses, **extra):
    d = {"camera_type": "perspective", "render_height": 12, "render_width": 16, "fps": 8, "seconds": 0.25,
         "camera_path": [{"camera_to_world": pose_to_nerfstudio(p).reshape(-1).tolist(), "fov": 60, "aspect": 4 / 3}
                         for p in poses]}
    d.update(extra)
    return d


def test_read_camera_path_converts_like_import(tmp_path):
    poses = [_pose(20, [0.5, -1.2, 0.3]), _pose(80, [1.0, -1.2, 0.8])]
    f = tmp_path / "camera_path.json"
    f.write_text(json.dumps(_camera_path(poses)))
    cp = read_camera_path(f)
    np.testing.assert_allclose(cp.poses, np.stack(poses), atol=1e-9)
    assert (cp.kind, cp.fov_deg, cp.height, cp.width, cp.fps) == ("perspective", 60, 12, 16, 8)
    assert cp.aspect == pytest.approx(4 / 3)


@pytest.mark.parametrize("patch, field", [
    ({"camera_path": []}, "camera_path"),
    ({"camera_type": "fisheye"}, "camera_type"),
    ({"render_height": -3}, "render_height"),
    ({"fps": "fast"}, "fps"),
    ({"camera_path": [{"camera_to_world": [1, 0, 0]}]}, "camera_path.0.camera_to_world"),
    ({"camera_path": [{"camera_to_world": [2, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]}]},
     "camera_path.0.camera_to_world"),
    ({"camera_path": [{"camera_to_world": np.eye(4).reshape(-1).tolist(), "fov": 0}]}, "camera_path.0.fov"),
])
def test_malformed_camera_path(tmp_path, patch, field):
    f = tmp_path / "cp.json"
    f.write_text(json.dumps(_camera_path([np.eye(4)], **patch)))
    with pytest.raises(PanoError) as e:
        read_camera_path(f)
    msg = str(e.value)
    assert str(f) in msg and field in msg and "\n" not in msg and e.value.exit_code == 2
    f.write_text("{not json")
    with pytest.raises(PanoError, match="cp.json"):
        read_camera_path(f)


# --- the command ---------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def run(sim_scene, sim_model, tmp_path_factory):
    pytest.importorskip("stages.train", reason="the train stage is not in this checkout yet")
    from evalhelpers import write_train_artifact

    run = tmp_path_factory.mktemp("flyrun") / "run"
    write_train_artifact(run, sim_model, resolution=(16, 32))
    return run


def _app():
    from evaluation.commands import render_command

    app = typer.Typer()
    app.command("render")(render_command)
    app.command("noop")(lambda: None)
    return app


def test_render_command_h264_names_and_file_paths(run, sim_scene):
    app = _app()
    args = ["render", str(sim_scene.root), "--out", str(run), "--frames", "3", "--height", "10"]
    r = CliRunner().invoke(app, args)
    assert r.exit_code == 0, r.output
    first = run / "render" / "flythrough-train-pano.mp4"
    meta, frames = _probe(first)
    assert meta["codec"] == "h264" and meta["size"] == (20, 10) and len(frames) == 3
    assert frames[1].std() > 5  # the room shows
    r = CliRunner().invoke(app, args)  # a rerun keeps the first video
    assert r.exit_code == 0 and "flythrough-train-pano-2.mp4" in r.output.replace("\n", "")
    assert (run / "render" / "flythrough-train-pano-2.mp4").is_file()
    before = first.stat().st_mtime_ns
    r = CliRunner().invoke(app, args + ["--overwrite"])
    assert r.exit_code == 0 and first.stat().st_mtime_ns != before
    assert not (run / "render" / "flythrough-train-pano-3.mp4").exists()
    # a nerfstudio camera path file through two views
    views = sim_scene.manifest.train_views()
    f = run.parent / "path.json"
    f.write_text(json.dumps(_camera_path([v.pose_matrix for v in views[:2]])))
    r = CliRunner().invoke(app, ["render", str(sim_scene.root), "--out", str(run), "--path", str(f)])
    assert r.exit_code == 0, r.output
    meta, frames = _probe(run / "render" / "flythrough-path-persp.mp4")
    assert meta["codec"] == "h264" and meta["size"] == (16, 12) and meta["fps"] == 8 and len(frames) == 2
    f.write_text(json.dumps(_camera_path([views[0].pose_matrix], camera_type="spherical")))
    r = CliRunner().invoke(app, ["render", str(sim_scene.root), "--out", str(run), "--path", str(f)])
    assert r.exit_code != 0 and isinstance(r.exception, PanoError) and "camera_type" in str(r.exception)
