"""cloud.npz / cloud.ply writer and reader shared by sampling, align and train."""

from __future__ import annotations

import numpy as np
import pytest

from runfs.errors import PanoError
from stages.cloud_io import read_cloud, write_cloud


def test_round_trip_and_ply(tmp_path):
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(50, 3))
    cols = rng.uniform(size=(50, 3))
    nrm = np.tile([0.0, -1.0, 0.0], (50, 1))
    files = write_cloud(tmp_path, pts, cols, nrm, pts + 0.1, np.arange(50) < 20)
    assert (files.npz, files.ply, files.num_points, files.num_layout_points) == (
        "cloud.npz",
        "cloud.ply",
        50,
        20,
    )
    c = read_cloud(tmp_path)  # the folder or the file
    c2 = read_cloud(tmp_path / "cloud.npz")
    for k in ("points", "colors", "normals", "u0"):
        assert c[k].dtype == np.float32 and c[k].shape == (50, 3)
        np.testing.assert_array_equal(c[k], c2[k])
    np.testing.assert_allclose(c["points"], pts, atol=1e-6)
    np.testing.assert_allclose(c["u0"], pts + 0.1, atol=1e-6)
    np.testing.assert_array_equal(c["is_layout"], np.arange(50) < 20)
    import open3d as o3d

    pc = o3d.io.read_point_cloud(str(tmp_path / "cloud.ply"))
    np.testing.assert_allclose(np.asarray(pc.points), pts, atol=1e-6)
    np.testing.assert_allclose(np.asarray(pc.normals), nrm, atol=1e-6)
    np.testing.assert_allclose(np.asarray(pc.colors), cols, atol=0.5 / 255 + 1e-6)  # 8-bit in PLY


def test_defaults_for_depth_points(tmp_path):
    pts = np.ones((4, 3))
    files = write_cloud(tmp_path, pts, np.full((4, 3), 255, np.uint8))
    c = read_cloud(tmp_path)
    assert files.num_layout_points == 0 and not c["is_layout"].any()
    np.testing.assert_array_equal(c["normals"], 0)
    np.testing.assert_array_equal(c["u0"], c["points"])
    np.testing.assert_array_equal(c["colors"], 1.0)
    empty = write_cloud(tmp_path / "e", np.zeros((0, 3)), np.zeros((0, 3)))
    assert empty.num_points == 0 and read_cloud(tmp_path / "e")["points"].shape == (0, 3)
    import open3d as o3d

    assert len(o3d.io.read_point_cloud(str(tmp_path / "e" / "cloud.ply")).points) == 0


def test_bad_arrays_and_files(tmp_path):
    with pytest.raises(ValueError, match="colors"):
        write_cloud(tmp_path, np.zeros((3, 3)), np.zeros((2, 3)))
    with pytest.raises(ValueError, match="NaN"):
        write_cloud(tmp_path, np.full((3, 3), np.nan), np.zeros((3, 3)))
    with pytest.raises(PanoError, match="not found"):
        read_cloud(tmp_path / "nope.npz")
    np.savez(tmp_path / "partial.npz", points=np.zeros((2, 3), np.float32))
    with pytest.raises(PanoError, match="missing arrays"):
        read_cloud(tmp_path / "partial.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(PanoError, match="unreadable"):
        read_cloud(tmp_path / "junk.npz")
    z = np.zeros((2, 3), np.float32)
    np.savez(
        tmp_path / "shape.npz", points=z, colors=z, normals=np.zeros((3, 3)), u0=z, is_layout=np.ones(2, bool)
    )
    with pytest.raises(PanoError, match="normals"):
        read_cloud(tmp_path / "shape.npz")
