"""SOG (PlayCanvas): our reader's round trip within the quantisation, the layout splat-transform
expects, and splat-transform's own reader (its CLI, when installed: `make setup-test` puts it in
.venv/node) agreeing with ours and with the PLY export."""

from __future__ import annotations

import io
import json
import os
import shutil
import subprocess
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch
from export_helpers import random_gaussians, run_cli

from export.sog import (kmeans, palette_size, quantize_1d, read_sog, sog_encode, sog_order, texture_size,
                        webp_decode, webp_encode, write_sog, zip_bytes)
from gaussians.ply import load_ply

ROOT = Path(__file__).resolve().parents[2]


def splat_transform() -> str | None:
    """The splat-transform CLI: $PANO_PIPE_SPLAT_TRANSFORM, the copy `make setup-test` installs, or PATH's
    (None without node to run it)."""
    if shutil.which("node") is None:
        return None
    for cand in (os.environ.get("PANO_PIPE_SPLAT_TRANSFORM"),
                 ROOT / ".venv/node/node_modules/.bin/splat-transform", shutil.which("splat-transform")):
        if cand and Path(cand).is_file() and os.access(cand, os.X_OK):
            return str(cand)
    return None


needs_splat_transform = pytest.mark.skipif(
    splat_transform() is None,
    reason="splat-transform CLI absent (`make setup-test` installs it where there is npm)")


def _np(t):
    return t.detach().double().numpy()


def _rotmats(q):
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                     2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                     2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], 1).reshape(-1, 3, 3)


def _few_sh_vectors(g, k: int = 8, seed: int = 0):
    """`g` with every Gaussian's SH bands 1.. one of k vectors (so the palette can hold them exactly)."""
    gen = torch.Generator().manual_seed(seed)
    base = (torch.rand(k, *g.sh_rest.shape[1:], generator=gen, dtype=g.sh_rest.dtype) - 0.5) * 0.6
    g.sh_rest = base[torch.arange(len(g)) % k]
    return g


def _nearest(values: np.ndarray, code: list[float]) -> np.ndarray:
    """Each value's distance to its nearest codebook entry."""
    c = np.asarray(code)
    return np.abs(values.reshape(-1, 1) - c[None]).min(1).reshape(values.shape)


def _check_quantised(back, g, meta):
    """`back` (decoded, texel order) is `g` (texel order) within what the SOG's quantisers allow."""
    lt = np.sign(_np(g.means)) * np.log1p(np.abs(_np(g.means)))
    step = (np.asarray(meta["means"]["maxs"]) - meta["means"]["mins"]) / 65535
    bound = 0.5 * step * np.exp(np.abs(lt) + step) + 1e-6  # half a 16-bit step of log(|x| + 1)
    np.testing.assert_array_less(np.abs(_np(back.means) - _np(g.means)), bound)
    # scales and colours: each value decodes to its nearest codebook entry
    for name, key in (("log_scales", "scales"), ("sh_dc", "sh0")):
        want = _nearest(_np(getattr(g, name)), meta[key]["codebook"])
        got = np.abs(_np(getattr(back, name)) - _np(getattr(g, name)))
        np.testing.assert_allclose(got, want, atol=5e-6, err_msg=name)
    np.testing.assert_allclose(torch.sigmoid(back.opacity_logits).double().numpy(),
                               torch.sigmoid(g.opacity_logits).double().numpy(), atol=0.5 / 255 + 1e-5)
    # 8 bits a component, ±√½ over 255 steps: each within 0.0028, a rotation matrix within ~0.02
    assert np.abs(_rotmats(_np(back.quats)) - _rotmats(_np(g.quats))).max() < 0.02


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_sog_round_trip_within_quantisation(tmp_path, degree):
    g = _few_sh_vectors(random_gaussians(300, degree=degree, seed=degree))
    files = sog_encode(g)
    path = tmp_path / "m.sog"
    path.write_bytes(zip_bytes(files))
    meta = json.loads(files["meta.json"])
    back = read_sog(path)
    gg = g.index(torch.as_tensor(files.order))
    assert len(back) == meta["count"] == len(g) and back.sh_degree == degree
    _check_quantised(back, gg, meta)
    if degree:  # 8 distinct SH vectors: the palette holds exactly them, the codebook their values
        assert meta["shN"]["bands"] == degree and meta["shN"]["count"] == 8 < palette_size(300) == 256
        assert np.abs(_np(back.sh_rest) - _np(gg.sh_rest)).max() < 5e-3
    else:
        assert "shN" not in meta and back.sh_rest.shape == (300, 0, 3)


def test_sog_layout_is_what_splat_transform_writes(tmp_path):
    g = random_gaussians(300, degree=3, seed=4)
    files = sog_encode(g)
    meta = json.loads(files["meta.json"])
    assert meta["version"] == 2 and meta["count"] == 300
    assert meta["means"]["files"] == ["means_l.webp", "means_u.webp"]
    assert meta["quats"]["files"] == ["quats.webp"]
    assert meta["shN"]["files"] == ["shN_centroids.webp", "shN_labels.webp"]
    for key in ("scales", "sh0", "shN"):
        assert len(meta[key]["codebook"]) == 256
        assert meta[key]["codebook"] == sorted(meta[key]["codebook"])
    assert texture_size(300) == (20, 16) and texture_size(36565) == (192, 192)
    assert all(w % 4 == 0 and h % 4 == 0 for w, h in map(texture_size, (1, 5, 17, 1000, 123457)))
    for name in ("means_l.webp", "means_u.webp", "quats.webp", "scales.webp", "sh0.webp", "shN_labels.webp"):
        assert files[name][:4] == b"RIFF" and files[name][12:16] == b"VP8L", name  # lossless WebP
        assert webp_decode(files[name]).shape == (16, 20, 4), name
    assert webp_decode(files["shN_centroids.webp"]).shape == (4, 64 * 15, 4)
    tags = webp_decode(files["quats.webp"]).reshape(-1, 4)[:300, 3]
    assert set(tags) <= {252, 253, 254, 255}
    # the bundle: an uncompressed zip, meta.json first, the same bytes for the same model
    raw = zip_bytes(files)
    with zipfile.ZipFile(io.BytesIO(raw)) as z:
        infos = z.infolist()
    assert infos[0].filename == "meta.json" and {i.compress_type for i in infos} == {zipfile.ZIP_STORED}
    assert sorted(i.filename for i in infos) == sorted(files)
    assert zip_bytes(sog_encode(g)) == raw
    # Morton order: consecutive texels are near each other
    order = sog_order(_np(g.means))
    assert np.array_equal(order, files.order) and sorted(order) == list(range(300))
    m = _np(g.means)
    step = lambda a: np.linalg.norm(np.diff(a, axis=0), axis=1).mean()  # noqa: E731
    assert step(m[order]) < 0.5 * step(m)


def test_webp_keeps_colour_under_zero_alpha():
    """The sh0 texture's alpha is opacity: a Gaussian with opacity 0 must keep its colour indices."""
    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (8, 12, 4), dtype=np.uint8)
    img[..., 3] = rng.choice([0, 1, 255], (8, 12))
    assert np.array_equal(webp_decode(webp_encode(img)), img)


def test_quantize_1d_keeps_the_tails():
    rng = np.random.default_rng(1)
    v = np.concatenate([rng.normal(-3.0, 0.3, 20000), [-12.0, 2.5, 3.0]])  # a dense centre, three outliers
    code, lab = quantize_1d(v)
    assert len(code) == 256 and np.all(np.diff(code) >= 0) and lab.dtype == np.uint8
    err = np.abs(code[lab] - v)
    assert np.array_equal(err, _nearest(v, code))  # nearest entry
    assert err[-3:].max() < 1e-12 and np.sqrt((err ** 2).mean()) < 0.005  # each outlier keeps an entry
    code, lab = quantize_1d(np.full(10, 0.25))
    assert np.all(code == 0.25) and np.all(lab == 0)


def test_kmeans_tree_and_matmul_searches_agree():
    """The CPU's k-d tree and the GPU's matrix products (run here on the CPU) find the same clusters;
    repeated points count once each time they occur; at most k distinct points come back exactly."""
    rng = np.random.default_rng(2)
    spread = [1, 1, 1, .1, .1, .1, .01, .01, .01]  # like SH bands 1..3: smaller and smaller
    pts = np.concatenate([rng.normal(size=(400, 9)) * spread, np.zeros((300, 9))])
    a_c, a_l = kmeans(pts, 64, search="tree")
    b_c, b_l = kmeans(pts, 64, search="matmul")
    np.testing.assert_allclose(a_c, b_c, atol=1e-5)
    assert np.array_equal(a_l, b_l) and np.all(a_l[400:] == a_l[400])  # the zeros share one cluster
    inertia = ((a_c[a_l] - pts) ** 2).sum()
    assert inertia < 0.5 * ((pts - pts.mean(0)) ** 2).sum()
    c, lab = kmeans(pts[395:], 64)  # 6 distinct points
    assert len(c) == 6 and np.array_equal(c[lab], pts[395:].astype(np.float32))


def test_sog_refuses_what_it_cannot_hold(tmp_path):
    g = random_gaussians(10, degree=0)
    g.means[0, 0] = float("nan")
    with pytest.raises(ValueError, match="non-finite"):
        write_sog(tmp_path / "bad.sog", g)
    (tmp_path / "x.sog").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="not a zip"):
        read_sog(tmp_path / "x.sog")


def test_sog_export_bundle_and_folder(run_copy, capsys, tmp_path):
    code, out = run_cli(["export", run_copy, "--format", "sog"], capsys)
    assert code == 0, out
    bundle = run_copy / "export" / "point_cloud.sog"
    assert f"wrote: {bundle}" in out
    folder = tmp_path / "web"
    code, out = run_cli(["export", run_copy, "--format", "sog", "--out", folder / "meta.json"], capsys)
    assert code == 0, out
    names = sorted(p.name for p in folder.iterdir())
    meta = json.loads((folder / "meta.json").read_text())
    listed = sorted(["meta.json"] + [f for k in ("means", "quats", "scales", "sh0", "shN") if k in meta
                                     for f in meta[k]["files"]])
    assert names == listed, "only the SOG's files, no temporaries"
    a, b = read_sog(bundle), read_sog(folder)
    for name, t in a.tensors().items():
        assert torch.equal(t, getattr(b, name)), name
    code, out = run_cli(["export", run_copy, "--format", "sog", "--out", folder / "meta.json"], capsys)
    assert code == 2 and "already exists" in out
    code, out = run_cli(["export", run_copy, "--format", "sog", "--out", tmp_path / "x.zip"], capsys)
    assert code == 2 and "meta.json" in out


def _splat_transform_to_ply(src: Path, dst: Path) -> None:
    r = subprocess.run([splat_transform(), "-q", "-w", str(src), str(dst)], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0 and dst.is_file(), r.stdout + r.stderr


@needs_splat_transform
def test_splat_transform_reads_our_sog_as_our_reader_does(tmp_path):
    g = random_gaussians(600, degree=3, seed=5)
    write_sog(tmp_path / "m.sog", g)
    _splat_transform_to_ply(tmp_path / "m.sog", tmp_path / "back.ply")
    theirs, ours = load_ply(tmp_path / "back.ply"), read_sog(tmp_path / "m.sog")
    assert len(theirs) == len(ours) == 600 and theirs.sh_degree == 3
    for name in ("means", "log_scales", "sh_dc", "sh_rest", "quats"):
        np.testing.assert_allclose(_np(getattr(theirs, name)), _np(getattr(ours, name)), atol=2e-6,
                                   err_msg=name)
    np.testing.assert_allclose(torch.sigmoid(theirs.opacity_logits).numpy(),
                               torch.sigmoid(ours.opacity_logits).numpy(), atol=1e-6)


@needs_splat_transform
def test_splat_transform_reads_the_exported_sog_as_the_ply_export(run_copy, capsys, tmp_path):
    for fmt in ("sog", "ply"):
        code, out = run_cli(["export", run_copy, "--format", fmt], capsys)
        assert code == 0, out
    _splat_transform_to_ply(run_copy / "export" / "point_cloud.sog", tmp_path / "back.ply")
    ply = load_ply(run_copy / "export" / "point_cloud.ply")
    back = load_ply(tmp_path / "back.ply")
    ply = ply.index(torch.as_tensor(sog_order(_np(ply.means))))  # the SOG's texel order
    with zipfile.ZipFile(run_copy / "export" / "point_cloud.sog") as z:
        meta = json.loads(z.read("meta.json"))
    _check_quantised(back, ply, meta)
    # colour as a viewer shows it (0.5 + C0·f_dc) within a few levels
    assert np.abs(_np(back.sh_dc) - _np(ply.sh_dc)).max() * 0.2821 < 4 / 255
