"""The depth stage on supplied files: PNG millimetres and NPY metres, masking, and bad files."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from runfs.errors import PanoError
from schemas.scene_loader import read_depth_file
from stages import depth as depth_stage


@pytest.fixture(scope="module")
def scene(dk, tmp_path_factory):
    return dk.make_encoded_scene(tmp_path_factory.mktemp("files") / "s", views=2, height=32, with_depth=True)


def test_png_millimetres_are_read_as_metres_along_the_ray(dk, scene, tmp_path):
    result, maps, _ = dk.run_depth(scene, tmp_path)
    assert [v.view for v in result.views] == [
        v.name for v in scene.manifest.train_views()
    ]  # test views unread
    for v in scene.manifest.train_views():
        d = maps[v.name]
        assert d.dtype == np.float32 and d.shape == (32, 64)
        assert np.nanmax(np.abs(d - dk.gt_depth(scene, v))) <= 0.0005 + 1e-6
        rv = next(r for r in result.views if r.view == v.name)
        assert rv.kind == "metric" and rv.source == "file" and rv.valid_fraction == 1.0


def test_npy_with_nan_zero_inf_and_far_pixels_is_masked(dk, scene, tmp_path):
    v = scene.manifest.train_views()[0]
    d = dk.gt_depth(scene, v).astype(np.float32)
    d[0, :5] = np.nan
    d[1, :5] = 0.0
    d[2, :5] = np.inf
    d[3, :5] = -1.0
    d[4, :5] = 500.0  # beyond far_limit
    path = tmp_path / "d.npy"
    np.save(path, d)
    out = depth_stage.mask_invalid(read_depth_file(path), "metric", 0.05, 100.0)
    assert np.isnan(out[:5, :5]).all()
    assert np.isfinite(out[5:]).all() and np.allclose(out[5:], d[5:])


def test_zero_in_png_is_invalid(tmp_path):
    mm = np.full((16, 32), 2500, np.uint16)
    mm[3, 4] = 0
    cv2.imwrite(str(tmp_path / "d.png"), mm)
    d = read_depth_file(tmp_path / "d.png")
    assert np.isnan(d[3, 4]) and np.isclose(np.nanmean(d), 2.5)


@pytest.mark.parametrize(
    "make,match",
    [
        (lambda p: np.save(p / "d.npy", np.ones((32, 50), np.float32)), "expected a 2:1"),
        (lambda p: np.save(p / "d.npy", np.ones((2, 16, 32), np.float32)), r"numeric \[H,W\]"),
        (lambda p: cv2.imwrite(str(p / "d.png"), np.full((16, 32), 9, np.uint8)), "16-bit single-channel"),
        (lambda p: (p / "d.png").write_bytes(b"not a png"), "unreadable depth PNG"),
    ],
)
def test_bad_depth_files_get_one_line_errors(tmp_path, make, match):
    make(tmp_path)
    path = next(tmp_path.glob("d.*"))
    with pytest.raises(PanoError, match=match) as e:
        read_depth_file(path)
    assert "\n" not in str(e.value) and str(path) in str(e.value)


def test_wrong_size_file_in_a_scene_fails_the_stage(dk, scene, tmp_path):
    import shutil

    bad = tmp_path / "bad"
    shutil.copytree(scene.root, bad)
    from schemas.scene_loader import load_scene

    s2 = load_scene(bad)
    v = s2.manifest.train_views()[0]
    cv2.imwrite(str(s2.depth_path(v)), np.full((20, 64), 1000, np.uint16))
    with pytest.raises(PanoError, match="64x20"):
        dk.run_depth(s2, tmp_path)


def test_skip_reason(dk, tmp_path):
    plain = dk.make_encoded_scene(tmp_path / "plain", views=1, height=16)
    assert "no depth" in depth_stage.skip_reason(plain, depth_stage.Params())
    assert depth_stage.skip_reason(plain, depth_stage.Params(model="m.onnx")) is None
