"""Metric tests against hand-computed and independently computed values."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import ndimage

from evalhelpers import write_fake_lpips_folder
from evaluation import metrics as M


def test_psnr_of_known_noise():
    gt = np.full((32, 64, 3), 0.5)
    sign = np.where((np.indices(gt.shape).sum(0) % 2) == 0, 1.0, -1.0)
    pred = gt + 0.1 * sign  # every pixel off by exactly 0.1: MSE = 0.01
    assert M.psnr(pred, gt) == pytest.approx(20.0, abs=1e-9)
    assert M.psnr(gt + 0.01, gt) == pytest.approx(40.0, abs=1e-9)
    # Gaussian noise of σ: PSNR ≈ −20·log10(σ)
    rng = np.random.default_rng(0)
    noisy = gt + rng.normal(0, 0.05, gt.shape)
    assert M.psnr(noisy, gt) == pytest.approx(-20 * math.log10(0.05), abs=0.1)


def test_psnr_identical_is_finite():
    x = np.random.default_rng(1).random((8, 16, 3))
    assert M.psnr(x, x) == pytest.approx(100.0)
    assert M.ws_psnr(x, x) == pytest.approx(100.0)


def test_ws_psnr_equals_psnr_on_latitude_uniform_error():
    rng = np.random.default_rng(2)
    gt = rng.random((32, 64, 3)) * 0.5
    row_err = np.abs(rng.normal(0, 0.1, (1, 64, 3)))  # same error in every row
    pred = gt + row_err
    assert M.ws_psnr(pred, gt) == pytest.approx(M.psnr(pred, gt), abs=1e-9)


def test_ws_psnr_discounts_the_poles():
    gt = np.zeros((32, 64, 3))
    polar = gt.copy()
    polar[0] = 0.5  # error only on the top row
    equator = gt.copy()
    equator[16] = 0.5  # the same error on a row next to the horizon
    assert M.psnr(polar, gt) == pytest.approx(M.psnr(equator, gt))
    assert M.ws_psnr(polar, gt) > M.psnr(polar, gt) + 10  # cos(θ) ~ 0.05 at the top row
    assert M.ws_psnr(equator, gt) < M.psnr(equator, gt)
    # hand value: weights cos θ_r, error 0.25 on one row
    w = np.cos((0.5 - (np.arange(32) + 0.5) / 32) * np.pi)
    assert M.ws_psnr(polar, gt) == pytest.approx(10 * math.log10(w.sum() / (0.25 * w[0])), abs=1e-9)


def test_ssim_of_identical_images_is_one():
    x = np.random.default_rng(3).random((24, 48, 3))
    assert M.ssim(x, x) == pytest.approx(1.0, abs=1e-12)


def _ssim_scipy(a, b):
    # Independent reference: separable Gaussian filtering with scipy, zero padding.
    g = M.gaussian_window(11, 1.5)

    def blur(t):
        t = ndimage.correlate1d(t, g, axis=0, mode="constant", cval=0.0)
        return ndimage.correlate1d(t, g, axis=1, mode="constant", cval=0.0)

    vals = []
    for ch in range(a.shape[2]):
        x, y = a[..., ch], b[..., ch]
        mx, my = blur(x), blur(y)
        sxx, syy, sxy = blur(x * x) - mx**2, blur(y * y) - my**2, blur(x * y) - mx * my
        c1, c2 = 0.01**2, 0.03**2
        vals.append(((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx**2 + my**2 + c1) * (sxx + syy + c2)))
    return float(np.mean(vals))


def test_ssim_matches_scipy_reference():
    rng = np.random.default_rng(4)
    a = ndimage.gaussian_filter(rng.random((40, 80, 3)), (2, 2, 0))
    b = np.clip(a + rng.normal(0, 0.05, a.shape), 0, 1)
    ref = _ssim_scipy(a, b)
    assert 0.2 < ref < 0.99
    assert M.ssim(a, b) == pytest.approx(ref, abs=1e-10)
    assert M.ssim(a, 1 - a) < ref  # inverted structure scores lower than noise


def test_ssim_of_constant_shift_hand_value():
    # Constant images, window 1 (no padding effect): σ = 0, so
    # SSIM = (2·μx·μy + C1)/(μx² + μy² + C1) at every pixel.
    a, b = np.full((8, 8), 0.5), np.full((8, 8), 0.3)
    c1 = 0.01**2
    want = (2 * 0.5 * 0.3 + c1) / (0.25 + 0.09 + c1)
    assert M.ssim(a, b, window=1) == pytest.approx(want, abs=1e-12)


def test_shape_mismatch_raises():
    with pytest.raises(ValueError, match="shapes differ"):
        M.psnr(np.zeros((4, 8, 3)), np.zeros((4, 9, 3)))


def test_depth_metrics_hand_example():
    gt = np.array([[1.0, 2.0], [4.0, 0.0]])  # 0 = no ground truth
    pred = np.array([[1.1, 1.8], [5.0, 3.0]])
    d = M.depth_metrics(pred, gt)
    assert d["count"] == 3
    assert d["abs_rel"] == pytest.approx((0.1 / 1 + 0.2 / 2 + 1.0 / 4) / 3)
    assert d["rmse"] == pytest.approx(math.sqrt((0.01 + 0.04 + 1.0) / 3))
    gt_nan = np.array([[np.nan, 2.0], [np.inf, -1.0]])
    d = M.depth_metrics(pred, gt_nan)
    assert d["count"] == 1 and d["abs_rel"] == pytest.approx(0.1)
    empty = M.depth_metrics(pred, np.zeros((2, 2)))
    assert empty["count"] == 0 and math.isnan(empty["rmse"])


def test_lpips_unavailable_reports_reason(tmp_path, monkeypatch):
    monkeypatch.setenv(M.LPIPS_ENV, str(tmp_path / "nowhere"))
    with pytest.raises(M.LpipsUnavailable, match="does not exist") as e:
        M.load_lpips("alex")
    assert M.LPIPS_ENV in str(e.value)
    (tmp_path / "empty").mkdir()
    with pytest.raises(M.LpipsUnavailable, match="lacks alexnet-owt-7be5be79.pth and alex.pth"):
        M.load_lpips("alex", weights=tmp_path / "empty")
    bad = tmp_path / "bad.pth"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(M.LpipsUnavailable, match="could not load"):
        M.load_lpips("alex", weights=bad)


def test_lpips_with_weights_present(tmp_path, monkeypatch):
    backbone, lin = write_fake_lpips_folder(tmp_path / "w")
    monkeypatch.setenv(M.LPIPS_ENV, str(tmp_path / "w"))
    model = M.load_lpips("alex")
    rng = np.random.default_rng(5)
    x = rng.random((64, 128, 3)).astype(np.float32)
    y = np.clip(x + rng.normal(0, 0.2, x.shape), 0, 1).astype(np.float32)
    assert model.distance(x, x) == pytest.approx(0.0, abs=1e-7)
    d1 = model.distance(x, y)
    assert d1 > 0
    assert model.distance(y, x) == pytest.approx(d1, rel=1e-5)
    # one merged file works too, and gives the same number
    merged = tmp_path / "merged.pth"
    torch.save({**backbone, **lin}, merged)
    assert M.load_lpips("alex", weights=merged).distance(x, y) == pytest.approx(d1, rel=1e-6)


def test_lpips_vgg_taps_match_heads():
    # VGG16 taps relu1_2 … relu5_3 feed 64/128/256/512/512-channel heads; a forward must run.
    model = M.LPIPS("vgg")
    x = torch.rand(1, 3, 32, 64)
    taps = model._taps(x)
    assert [t.shape[1] for t in taps] == [64, 128, 256, 512, 512]
    assert [t.shape[2] for t in taps] == [32, 16, 8, 4, 2]
    assert float(model(x, x)[0]) == 0.0
    with pytest.raises(M.LpipsUnavailable, match="unknown LPIPS backbone"):
        M.find_lpips_weights("resnet")
