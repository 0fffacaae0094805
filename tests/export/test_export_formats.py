"""Round trips of every Gaussian format within its quantisation."""

from __future__ import annotations

import gzip

import numpy as np
import pytest
import torch
from export_helpers import random_gaussians

from runfs.fsutil import atomic_write
from export.splat import SPLAT_DTYPE, read_splat, splat_order, write_splat
from export.spz import MAGIC, read_spz, spz_bytes, spz_header, write_spz
from export.transform import to_y_up
from gaussians.model import SH_C0
from gaussians.ply import load_ply, save_ply


def _np(t):
    return t.detach().double().numpy()


def _rotmats(q: np.ndarray) -> np.ndarray:
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], 1).reshape(-1, 3, 3)


def test_ply_round_trip_is_exact(model, tmp_path):
    path = atomic_write(tmp_path / "m.ply", lambda tmp: save_ply(tmp, model))
    back = load_ply(path)
    for name in ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest", "normals"):
        assert torch.equal(getattr(back, name), getattr(model, name)), name
    assert not list(tmp_path.glob(".*tmp*")), "temporary file left behind"


def test_splat_round_trip_within_quantisation(model, tmp_path):
    path = write_splat(tmp_path / "m.splat", model)
    assert path.stat().st_size == 32 * len(model) and SPLAT_DTYPE.itemsize == 32
    s = read_splat(path)
    order = splat_order(model)
    g = model.index(torch.as_tensor(order))
    np.testing.assert_array_equal(s["means"], _np(g.means))
    np.testing.assert_allclose(s["scales"], np.exp(_np(g.log_scales)), rtol=1e-6)
    rgb = np.clip(0.5 + SH_C0 * _np(g.sh_dc).reshape(-1, 3), 0, 1)
    np.testing.assert_allclose(s["rgb"], rgb, atol=0.5 / 255 + 1e-6)
    np.testing.assert_allclose(s["alpha"], torch.sigmoid(g.opacity_logits).double().numpy(), atol=0.5 / 255 + 1e-6)
    q = _np(g.quats)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    np.testing.assert_allclose(s["quats"], np.clip(q, -1, 127 / 128), atol=0.5 / 128 + 1e-6)
    # sorted by decreasing importance = scale product × opacity, as antimatter15's convert.py
    imp = np.prod(s["scales"], 1) * s["alpha"]
    assert np.all(np.diff(np.prod(np.exp(_np(g.log_scales)), 1) * torch.sigmoid(g.opacity_logits).double().numpy())
                  <= 1e-12)
    assert np.corrcoef(imp, np.arange(len(imp)))[0, 1] < 0


def test_splat_rejects_a_partial_record(tmp_path):
    (tmp_path / "bad.splat").write_bytes(b"\0" * 33)
    with pytest.raises(ValueError, match="32-byte"):
        read_splat(tmp_path / "bad.splat")


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_spz_round_trip_within_quantisation(tmp_path, degree):
    model = random_gaussians(300, degree=degree, seed=degree)
    path = write_spz(tmp_path / "m.spz", model)
    raw = gzip.decompress(path.read_bytes())
    h = spz_header(raw)
    assert (h["magic"], h["version"], h["num_points"], h["sh_degree"], h["fractional_bits"]) == (
        MAGIC, 3, len(model), degree, 12)
    back = read_spz(path)
    np.testing.assert_allclose(_np(back.means), _np(model.means), atol=0.5 / 4096 + 1e-6)
    np.testing.assert_allclose(_np(back.log_scales), _np(model.log_scales), atol=0.5 / 16 + 1e-5)
    np.testing.assert_allclose(torch.sigmoid(back.opacity_logits).double().numpy(),
                               torch.sigmoid(model.opacity_logits).double().numpy(), atol=0.5 / 255 + 1e-4)
    np.testing.assert_allclose(_np(back.sh_dc), _np(model.sh_dc), atol=0.5 / (0.15 * 255) + 1e-5)
    # rotations: smallest three at 9 bits + sign -> the rotation matrices agree to ~1e-2
    err = np.abs(_rotmats(_np(back.quats)) - _rotmats(_np(model.quats))).max()
    assert err < 0.01, err
    assert np.allclose(np.linalg.norm(_np(back.quats), axis=1), 1, atol=1e-5)
    if degree:
        d = np.abs(_np(back.sh_rest) - _np(model.sh_rest))
        assert d[:, :3].max() <= 4.5 / 128 + 1e-6  # band 1: 5 bits
        assert d[:, 3:].max(initial=0) <= 8.5 / 128 + 1e-6  # bands 2-3: 4 bits


def test_spz_stores_rub_so_y_up_gives_the_same_file(model):
    assert spz_bytes(model) == spz_bytes(to_y_up(model), rub=True)
    # the stored frame is y up: the first point's stored y is minus ours
    raw = gzip.decompress(spz_bytes(model))
    b = np.frombuffer(raw[16:25], dtype=np.uint8).astype(np.int64)
    y = b[3] | (b[4] << 8) | (b[5] << 16)
    y = (y - (1 << 24) if y & 0x800000 else y) / 4096
    assert abs(y + float(model.means[0, 1])) < 1e-3


def test_spz_refuses_what_does_not_fit(tmp_path):
    far = random_gaussians(4)
    far.means[0, 0] = 5000.0
    with pytest.raises(ValueError, match="24-bit"):
        spz_bytes(far)
    (tmp_path / "x.spz").write_bytes(gzip.compress(b"NOPE" + b"\0" * 12))
    with pytest.raises(ValueError, match="magic"):
        read_spz(tmp_path / "x.spz")
    (tmp_path / "y.spz").write_bytes(b"not gzip")
    with pytest.raises(ValueError, match="gzip"):
        read_spz(tmp_path / "y.spz")
