"""Valid-pixel masks (per-view files and the nadir cap): a masked-out region's content has no
effect on the losses, the densification signal, the metrics or depth back-projection; bad masks
are one-line errors."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from evaluation import metrics as M
from gaussians.losses import l1_loss, photometric_loss, psnr, ssim
from panogeom.equirect import nadir_cap, row_latitudes
from schemas.scene_loader import load_scene, valid_mask
from simulate.generate import generate_scene
from tests.clitools import invoke


def images(h=16, w=32, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(h, w, 3, generator=g), torch.rand(h, w, 3, generator=g)


def bottom_mask(h=16, w=32, rows=4):
    m = torch.ones(h, w, dtype=torch.bool)
    m[-rows:] = False
    return m


def scribble(x, mask, value):
    """x with every masked-out pixel replaced by `value`."""
    return torch.where(mask[..., None], x, torch.full_like(x, value))


# ----------------------------------------------------------------------------- losses
def test_masked_content_has_no_effect_on_the_losses():
    pred, gt = images()
    mask = bottom_mask()
    for fn in (lambda p, g: l1_loss(p, g, mask), lambda p, g: ssim(p, g, mask=mask),
               lambda p, g: photometric_loss(p, g, 0.8, 0.2, mask=mask)[0]):
        ref = float(fn(pred, gt))
        assert float(fn(scribble(pred, mask, 0.0), scribble(gt, mask, 1.0))) == pytest.approx(ref, abs=1e-7)
    assert psnr(scribble(pred, mask, 1.0), gt, mask) == pytest.approx(psnr(pred, gt, mask), abs=1e-6)


def test_masked_pixels_get_no_gradient():
    pred, gt = images()
    mask = bottom_mask()
    pred.requires_grad_(True)
    photometric_loss(pred, gt, 0.8, 0.2, mask=mask)[0].backward()
    assert float(pred.grad[~mask].abs().max()) == 0.0
    assert float(pred.grad[mask].abs().max()) > 0.0


def test_an_all_invalid_mask_is_finite_not_0_over_0():
    pred, gt = images()
    none = torch.zeros(16, 32, dtype=torch.bool)
    pred.requires_grad_(True)
    loss = photometric_loss(pred, gt, 0.8, 0.2, mask=none)[0]
    loss.backward()
    assert torch.isfinite(loss) and bool(torch.isfinite(pred.grad).all())
    assert np.isfinite(psnr(pred, gt, none))


def test_a_full_mask_equals_no_mask():
    pred, gt = images()
    full = torch.ones(16, 32, dtype=torch.bool)
    assert float(l1_loss(pred, gt, full)) == pytest.approx(float(l1_loss(pred, gt)), rel=1e-6)
    assert psnr(pred, gt, full) == pytest.approx(psnr(pred, gt), rel=1e-6)


# ----------------------------------------------------------------------------- metrics
def test_masked_content_has_no_effect_on_the_metrics():
    pred, gt = (x.numpy().astype(np.float64) for x in images(seed=3))
    mask = bottom_mask().numpy()
    p2, g2 = pred.copy(), gt.copy()
    p2[~mask], g2[~mask] = 0.0, 1.0
    for fn in (M.psnr, M.ssim, M.ws_psnr):
        assert fn(p2, g2, mask=mask) == pytest.approx(fn(pred, gt, mask=mask), abs=1e-9)
        assert fn(p2, g2, mask=mask) != pytest.approx(fn(p2, g2), abs=1e-3)  # the mask matters


# ----------------------------------------------------------------------------- the nadir cap
def test_nadir_cap_masks_the_rows_within_its_radius():
    h, w = 64, 128
    cap = nadir_cap(h, w, 20.0)
    lat = np.rad2deg(row_latitudes(h))
    assert cap.shape == (h, w)
    assert np.array_equal(cap[:, 0], lat > -70.0) and (cap == cap[:, :1]).all()
    assert 0.10 < 1 - cap.mean() < 0.12  # 20° of 180°
    assert nadir_cap(h, w, 0.0).all()


# ----------------------------------------------------------------------------- scenes
@pytest.fixture(scope="module")
def base(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("masks") / "S"
    generate_scene(root, views=3, test_views=1, height=16, effects="none", with_layout=True, with_depth=True)
    return root


@pytest.fixture
def scene(base, tmp_path, monkeypatch) -> Path:
    shutil.copytree(base, tmp_path / "S")
    monkeypatch.chdir(tmp_path)
    return tmp_path / "S"


def write_mask(scene: Path, view: str, valid: np.ndarray) -> Path:
    (scene / "masks").mkdir(exist_ok=True)
    path = scene / "masks" / f"{view}.png"
    cv2.imwrite(str(path), valid.astype(np.uint8) * 255)
    return path


def test_masks_are_found_by_name_resized_and_combined_with_the_nadir_cap(scene):
    valid = np.ones((16, 32), bool)
    valid[:, :4] = False
    write_mask(scene, "train_00", valid)
    data = json.loads((scene / "scene.json").read_text())
    data["nadir_mask_deg"] = 30
    (scene / "scene.json").write_text(json.dumps(data))
    s = load_scene(scene)
    m = valid_mask(s, s.manifest.view("train_00"), 8, 16)
    assert m.shape == (8, 16) and not m[:, :2].any() and m[0, 8]
    assert not m[-1].any()  # the bottom row lies inside a 30° cap
    other = valid_mask(s, s.manifest.view("train_01"), 8, 16)
    assert np.array_equal(other, nadir_cap(8, 16, 30))


@pytest.mark.parametrize("problem", ["size", "unreadable", "empty"])
def test_bad_masks_are_one_line_errors(scene, problem, capsys):
    path = scene / "masks" / "train_01.png"
    if problem == "size":
        write_mask(scene, "train_01", np.ones((10, 20), bool))
        expected = "a mask has its image's size"
    elif problem == "unreadable":
        (scene / "masks").mkdir()
        path.write_bytes(b"not a png")
        expected = "unreadable mask"
    else:
        write_mask(scene, "train_01", np.zeros((16, 32), bool))
        expected = "leaves no valid pixel"
    code, out, err = invoke(["status", scene, "--out", scene.parent / "R"], capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1
    assert str(path) in err and expected in err


def test_training_and_metrics_ignore_a_masked_tripod(scene, capsys):
    """A black blob painted into the bottom rows of every view, masked out: the run trains, the
    metrics are those of the valid pixels, and the evaluate artifact says which mask it used."""
    data = json.loads((scene / "scene.json").read_text())
    for v in data["views"]:
        img = cv2.imread(str(scene / v["image"]))
        img[-3:] = 0
        cv2.imwrite(str(scene / v["image"]), img)
        valid = np.ones(img.shape[:2], bool)
        valid[-3:] = False
        write_mask(scene, v["name"], valid)
    code, out, err = invoke(["run", "all", scene, "--out", scene.parent / "R", "--set", "train.iterations=5",
                             "--set", "train.height=8", "--set", "evaluate.fps_repeats=1"], capsys)
    assert code == 0, err
    ev = json.loads((scene.parent / "R" / "evaluate" / "artifact.json").read_text())["data"]
    assert ev["views"][0]["mask"] == "masks/test_00.png"
    # the metric is the valid pixels' one: recompute it from the written images
    rnd = cv2.imread(str(scene.parent / "R" / "evaluate" / ev["views"][0]["render"]))[..., ::-1] / 255.0
    gt = cv2.imread(str(scene.parent / "R" / "evaluate" / ev["views"][0]["gt"]))[..., ::-1] / 255.0
    s = load_scene(scene)
    mask = valid_mask(s, s.manifest.view("test_00"), *gt.shape[:2])
    assert ev["views"][0]["psnr"] == pytest.approx(M.psnr(rnd, gt, mask=mask), abs=0.05)
    assert ev["views"][0]["psnr"] != pytest.approx(M.psnr(rnd, gt), abs=0.05)


def test_cube_faces_carry_the_mask_and_a_wholly_masked_face_is_dropped():
    from stages.train import build_views

    h, w = 16, 32
    img = np.random.default_rng(0).random((h, w, 3)).astype(np.float32)
    mask = nadir_cap(h, w, 60.0)  # the whole bottom face lies inside
    views = build_views({"a": img}, {"a": np.eye(4)}, "cubemap", {"a": mask})
    names = [v.name.split("/")[1] for v in views]
    assert len(views) == 5 and all(v.mask is not None and bool(v.mask.any()) for v in views)
    assert len(set(names)) == 5
    full = build_views({"a": img}, {"a": np.eye(4)}, "cubemap", {"a": None})
    assert len(full) == 6 and all(v.mask is None for v in full)


def test_align_does_not_back_project_masked_pixels(scene, capsys):
    code, out, err = invoke(["run", "align", scene, "--out", scene.parent / "R"], capsys)
    assert code == 0, err
    full = json.loads((scene.parent / "R" / "align" / "artifact.json").read_text())["data"]
    data = json.loads((scene / "scene.json").read_text())
    data["nadir_mask_deg"] = 45
    (scene / "scene.json").write_text(json.dumps(data))
    code, out, err = invoke(["run", "align", scene, "--out", scene.parent / "R"], capsys)
    assert code == 0, err
    capped = json.loads((scene.parent / "R" / "align" / "artifact.json").read_text())["data"]

    def depth_points(d):
        return d["cloud"]["num_points"] - d["cloud"]["num_layout_points"]

    # the cap's pixels are neither fitted nor back-projected
    assert capped["fits"][0]["num_pixels"] < full["fits"][0]["num_pixels"]
    assert depth_points(capped) < depth_points(full)


def test_the_report_says_which_mask_was_applied(scene, capsys):
    data = json.loads((scene / "scene.json").read_text())
    data["nadir_mask_deg"] = 15
    (scene / "scene.json").write_text(json.dumps(data))
    args = ["--out", scene.parent / "R"]
    code, out, err = invoke(["run", "all", scene, *args, "--set", "train.iterations=3", "--set", "train.height=8",
                             "--set", "evaluate.fps_repeats=1"], capsys)
    assert code == 0, err
    code, out, err = invoke(["report", scene, *args], capsys)
    assert code == 0, err
    md = (scene.parent / "R" / "report" / "report.md").read_text()
    assert "masks applied: test_00: nadir cap 15°" in md
