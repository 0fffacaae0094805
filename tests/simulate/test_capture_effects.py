"""The capture effects: per-view exposure / white balance and the tripod at the nadir.

Checked against the ground truth the simulator keeps for them (gt/clean, gt/masks,
gt/exposure.json), read from disk.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

import simulate

H = 64  # small: the suite must stay fast on a shared 2-core machine


def _make(root: Path, effects: str, seed: int = 4, preset: str = "cuboid", views: int = 3) -> Path:
    simulate.generate_scene(root, preset=preset, views=views, test_views=1, height=H, seed=seed,
                            effects=effects, aa_samples=2)
    return root


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    """effects -> scene folder, generated lazily (the same seed for all)."""
    base = tmp_path_factory.mktemp("capture")

    class _Lazy(dict):
        def __missing__(self, fx):
            self[fx] = _make(base / fx.replace(",", "_"), fx)
            return self[fx]

    return _Lazy()


def _rgb(path: Path) -> np.ndarray:
    return cv2.cvtColor(cv2.imread(str(path), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB).astype(np.float64)


def _views(root: Path) -> list[str]:
    return [v["name"] for v in json.loads((root / "scene.json").read_text())["views"]]


def _mask(root: Path, view: str) -> np.ndarray:
    m = cv2.imread(str(root / "gt" / "masks" / f"{view}.png"), cv2.IMREAD_UNCHANGED)
    assert m.dtype == np.uint8 and m.shape == (H, 2 * H)
    assert set(np.unique(m)) <= {0, 255}
    return m


def _digest(root: Path) -> dict[str, str]:
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file() and p.name != "scene.json"  # names the scene after its folder
    }


# ----------------------------------------------------------------------------- gt files


@pytest.mark.parametrize(
    "effects, clean, masks, exposure",
    [
        ("texture,shading", False, False, False),
        ("noise", False, False, False),
        ("exposure", True, False, True),
        ("tripod", True, True, False),
        ("tripod,exposure,noise", True, True, True),
    ],
)
def test_gt_files_only_for_listed_effects(capture, effects, clean, masks, exposure):
    root = capture[effects]
    assert (root / "gt" / "clean").is_dir() == clean
    assert (root / "gt" / "masks").is_dir() == masks
    assert (root / "gt" / "exposure.json").is_file() == exposure
    for v in _views(root):
        if clean:
            assert (root / "gt" / "clean" / f"{v}.png").is_file()
        if masks:
            assert (root / "gt" / "masks" / f"{v}.png").is_file()
    # scene.json keeps its schema: no mask is supplied as an input.
    assert all("mask" not in v for v in json.loads((root / "scene.json").read_text())["views"])
    assert not (root / "masks").exists()


# ----------------------------------------------------------------------------- exposure


def _check_ratio(img: np.ndarray, clean: np.ndarray, gains: np.ndarray, valid: np.ndarray) -> None:
    """img = round(clip(c * g) * 255), clean = round(c * 255): |img - g clean| <= 0.5 + 0.5 g
    wherever the image is not clipped."""
    for c in range(3):
        ok = valid & (img[..., c] < 255) & (clean[..., c] >= 16)
        assert ok.mean() > 0.5
        err = np.abs(img[..., c][ok] - gains[c] * clean[..., c][ok])
        assert err.max() <= 0.5 + 0.5 * gains[c] + 1e-6, f"channel {c}: {err.max():.3f}"
        fit = (img[..., c][ok] * clean[..., c][ok]).sum() / (clean[..., c][ok] ** 2).sum()
        assert fit == pytest.approx(gains[c], rel=0.01)


def test_exposure_ratio_matches_recorded_gains(capture):
    root = capture["exposure"]
    rec = json.loads((root / "gt" / "exposure.json").read_text())["views"]
    assert set(rec) == set(_views(root))
    for v, p in rec.items():
        g, wb, cg = p["gain"], np.asarray(p["white_balance"]), np.asarray(p["channel_gains"])
        assert 0.75 <= g <= 1.25
        assert wb[1] == 1.0 and np.all(np.abs(wb - 1.0) <= 0.08)
        np.testing.assert_allclose(cg, g * wb, rtol=1e-12)
        img, clean = _rgb(root / "images" / f"{v}.png"), _rgb(root / "gt" / "clean" / f"{v}.png")
        _check_ratio(img, clean, cg, np.ones(img.shape[:2], bool))
    # Different per view.
    assert len({round(p["gain"], 9) for p in rec.values()}) == len(rec)
    assert len({round(p["white_balance"][0], 9) for p in rec.values()}) == len(rec)


def test_clean_image_is_the_effect_free_render(capture):
    """gt/clean is what the image would be without the capture effects (same seed, same scene)."""
    a, b = capture["exposure"], capture["tripod"]
    plain = _make(a.parent / "plain", "none")
    for v in _views(a):
        ref = cv2.imread(str(plain / "images" / f"{v}.png"))
        assert np.array_equal(cv2.imread(str(a / "gt" / "clean" / f"{v}.png")), ref)
        assert np.array_equal(cv2.imread(str(b / "gt" / "clean" / f"{v}.png")), ref)


def test_noise_is_sensor_noise_only(capture):
    """`noise` no longer changes the exposure: the mean level stays, the noise is small."""
    noisy, plain = capture["noise"], _make(capture["noise"].parent / "plain-n", "none")
    for v in _views(noisy):
        d = _rgb(noisy / "images" / f"{v}.png") - _rgb(plain / "images" / f"{v}.png")
        assert abs(d.mean()) < 0.5 and 1.0 < d.std() < 6.0


# ----------------------------------------------------------------------------- tripod


def test_tripod_mask_at_the_nadir(capture):
    root = capture["tripod"]
    masks = []
    for v in _views(root):
        m = _mask(root, v)
        covered = m == 0
        rows = np.flatnonzero(covered.any(axis=1))
        assert rows.min() >= int(0.88 * H), f"{v}: tripod reaches row {rows.min()} of {H}"
        assert covered[-1].all()  # the nadir itself is covered
        frac = covered.mean()
        assert 0.05 <= frac <= 0.10, f"{v}: area fraction {frac:.4f}"
        # Rows above the blob's lowest boundary are fully covered below it (star-shaped about the nadir).
        top = np.argmax(covered, axis=0)
        assert all(covered[t:, c].all() for c, t in enumerate(top))
        masks.append(m)
        # Outside the mask the image is the clean image; inside it is dark.
        img, clean = _rgb(root / "images" / f"{v}.png"), _rgb(root / "gt" / "clean" / f"{v}.png")
        assert np.array_equal(img[~covered], clean[~covered])
        assert img[covered].mean() < 40 and img[covered].mean() < 0.5 * clean[covered].mean()
        assert img[covered].std() > 1.0  # roughly textured, not a flat fill
    for i in range(len(masks)):
        for j in range(i + 1, len(masks)):
            assert (masks[i] != masks[j]).mean() > 0.002, "tripod masks identical between views"


def test_tripod_with_exposure_and_noise(capture):
    """All capture effects: the exposure ratio holds outside the tripod (noise aside), and the
    tripod and exposure draws are independent of the other effects."""
    root = capture["tripod,exposure"]
    rec = json.loads((root / "gt" / "exposure.json").read_text())["views"]
    alone = json.loads((capture["exposure"] / "gt" / "exposure.json").read_text())["views"]
    assert rec == alone  # toggling the tripod does not change the exposure draws
    for v in _views(root):
        m = _mask(root, v)
        assert np.array_equal(m, _mask(capture["tripod"], v))  # nor the exposure the tripod
        img, clean = _rgb(root / "images" / f"{v}.png"), _rgb(root / "gt" / "clean" / f"{v}.png")
        _check_ratio(img, clean, np.asarray(rec[v]["channel_gains"]), m == 255)
    full = capture["tripod,exposure,noise"]
    assert json.loads((full / "gt" / "exposure.json").read_text())["views"] == rec
    for v in _views(full):
        assert np.array_equal(_mask(full, v), _mask(root, v))


def test_capture_effects_deterministic_per_seed(tmp_path):
    fx = "tripod,exposure,noise"
    a, b = _make(tmp_path / "a", fx, seed=9, views=2), _make(tmp_path / "b", fx, seed=9, views=2)
    c = _make(tmp_path / "c", fx, seed=10, views=2)
    da, db, dc = _digest(a), _digest(b), _digest(c)
    assert da == db
    assert da["gt/masks/train_00.png"] != dc["gt/masks/train_00.png"]
    assert da["gt/exposure.json"] != dc["gt/exposure.json"]
