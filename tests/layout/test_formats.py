"""Supplied layout formats: round trips against analytic rooms, and one-line errors."""

from __future__ import annotations

import json

import numpy as np
import pytest
from layout_helpers import L_SHAPE, exact_boundaries, match_corners, world_to_camera_xz

from layoutnet import postprocess as pp
from layoutnet.formats import horizonnet_json, read_layout
from runfs.errors import PanoError

H_CAM, H_ROOM = 1.45, 2.7


def _room_from(sup, h=H_CAM, width=256):
    """The room and the source's boundaries, with the layout stage's default wall fitting."""
    from layoutnet.rooms import room_from_supplied
    from stages.layout import Params, wall_fit

    got = room_from_supplied(sup, h, width, **wall_fit(Params()))
    assert got.boundaries.shape == (2, width) and got.confidence.shape == (width,)
    return got.room, got.raw


@pytest.mark.parametrize("size", [(512, 1024), (64, 128)])
def test_horizonnet_json_round_trip(tmp_path, size):
    true = world_to_camera_xz(L_SHAPE, (0.2, -0.1), 0.6)
    data = horizonnet_json(true, H_CAM, H_ROOM - H_CAM, width=size[1], height=size[0])
    assert data["z0"] == 50.0 and data["z1"] == pytest.approx(-50 * H_CAM / (H_ROOM - H_CAM))
    p = tmp_path / "v.json"
    p.write_text(json.dumps(data))
    sup = read_layout(p, size[1], size[0])
    assert sup.kind == "json" and sup.corners.shape == (6, 3)
    room, raw = _room_from(sup)
    assert raw is None and room.method == "corners"
    assert match_corners(room.polygon, true) < 1e-9
    assert room.ceiling_distance == pytest.approx(H_ROOM - H_CAM)


def test_corner_txt_in_pixels(tmp_path):
    """PanoContext/Stanford corners: "x y" pixel pairs (ceiling, floor), here on a 1024x512 panorama."""
    true = world_to_camera_xz(L_SHAPE, (0.2, -0.1), 0.6)
    w, h = 1024, 512
    phi = np.arctan2(true[:, 0], true[:, 1])
    d = np.hypot(true[:, 0], true[:, 1])
    lines = ["# x y"]
    for j in np.argsort(phi):
        x = (phi[j] / (2 * np.pi) + 0.5) * w - 0.5
        for th in (np.arctan2(H_ROOM - H_CAM, d[j]), -np.arctan2(H_CAM, d[j])):
            lines.append(f"{x:.6f} {(0.5 - th / np.pi) * h - 0.5:.6f}")
    p = tmp_path / "v.txt"
    p.write_text("\n".join(lines) + "\n")
    room, _ = _room_from(read_layout(p, w, h))
    assert match_corners(room.polygon, true) < 1e-4  # 6 printed decimals of a pixel
    assert room.ceiling_distance == pytest.approx(H_ROOM - H_CAM, abs=1e-4)


def test_npy_boundaries_go_through_the_wall_fitting(tmp_path):
    b = exact_boundaries(L_SHAPE, (0.2, -0.1), H_CAM, H_ROOM, 512, 0.6)
    p = tmp_path / "v.npy"
    np.save(p, b.astype(np.float32))
    sup = read_layout(p)
    room, raw = _room_from(sup)
    assert room.method == "manhattan" and raw.shape == (2, 512)
    assert match_corners(room.polygon, world_to_camera_xz(L_SHAPE, (0.2, -0.1), 0.6)) < 0.01
    assert abs(room.ceiling_distance - (H_ROOM - H_CAM)) < 0.01


def _err(path, **kw) -> str:
    with pytest.raises(PanoError) as ei:
        read_layout(path, **kw)
    msg = str(ei.value)
    assert "\n" not in msg and str(path) in msg
    return msg


@pytest.mark.parametrize(
    "text,problem",
    [
        ("{not json", "not valid JSON"),
        ('{"z0": 50, "z1": -60}', "expected HorizonNet layout JSON"),
        ('{"uv": [[0.1, 0.3], [0.1, 0.7], [0.4, 0.3]]}', "odd count"),
        ('{"uv": [[0.1, 0.3], [0.1, 0.7], [0.4, 0.3], [0.4, 0.7]]}', "at least 3 corners"),
        (
            '{"uv": [[0.1, 0.3], [0.1, 1.7], [0.4, 0.3], [0.4, 0.7], [0.7, 0.3], [0.7, 0.7]]}',
            "normalised to [0, 1]",
        ),
        (
            '{"uv": [[0.1, 0.3], [0.1, 0.4], [0.4, 0.3], [0.4, 0.7], [0.7, 0.3], [0.7, 0.7]]}',
            "floor point below",
        ),
        (
            '{"z0": 50, "z1": 60, '
            '"uv": [[0.1, 0.3], [0.1, 0.7], [0.4, 0.3], [0.4, 0.7], [0.7, 0.3], [0.7, 0.7]]}',
            '"z1" < 0',
        ),
        ('{"uv": "corners"}', "pairs"),
    ],
)
def test_malformed_json(tmp_path, text, problem):
    p = tmp_path / "bad.json"
    p.write_text(text)
    assert problem in _err(p)


@pytest.mark.parametrize(
    "text,problem",
    [
        ("10 100\n10 400\n300 100\n300 abc\n", "line 4"),
        ("10 100\n10 400\n300 100\n", "odd count"),
        ("10 100\n10 400\n300 100\n300 400\n600 100\n600 400\n2000 100\n2000 400\n", "outside the 1024x512"),
        ("1 2 3\n", "line 1"),
    ],
)
def test_malformed_txt(tmp_path, text, problem):
    p = tmp_path / "bad.txt"
    p.write_text(text)
    assert problem in _err(p, width=1024, height=512)


def test_malformed_npy(tmp_path):
    b = exact_boundaries(L_SHAPE, (0.2, -0.1), H_CAM, H_ROOM, 64, 0.0)
    cases = {
        "shape.npy": (b.T, "expected [2,W]"),
        "bon.npy": (-b, "looks like HorizonNet's `bon`"),
        "nan.npy": (np.where(np.arange(64) == 3, np.nan, b), "NaN"),
        "int.npy": (np.ones((2, 64), dtype=np.int32), "float latitudes"),
        "degrees.npy": (np.degrees(b), "radians"),
    }
    for name, (arr, problem) in cases.items():
        np.save(tmp_path / name, arr)
        assert problem in _err(tmp_path / name), name
    (tmp_path / "text.npy").write_text("not an array")
    assert "not a readable .npy" in _err(tmp_path / "text.npy")


def test_missing_and_unknown_files(tmp_path):
    assert "does not exist" in _err(tmp_path / "none.json")
    (tmp_path / "v.csv").write_text("1,2")
    assert "unknown layout format" in _err(tmp_path / "v.csv")


def test_boundary_sign_helper_is_consistent_with_pixel_rows():
    """DESIGN.md: row r = (0.5 - theta/pi) H - 0.5; HorizonNet's coory2v is the inverse."""
    from layoutnet.formats import pixel_to_angles

    phi, th = pixel_to_angles(np.array([0.0, 511.5]), np.array([0.0, 255.5]), 1024, 512)
    assert th[1] == pytest.approx(0.0) and phi[1] == pytest.approx(0.0, abs=1e-12)
    assert th[0] == pytest.approx(np.pi / 2 - np.pi / 1024)
    assert pp.check_boundaries(np.array([[0.3] * 8, [-0.2] * 8])).shape == (2, 8)
