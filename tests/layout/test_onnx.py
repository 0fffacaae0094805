"""The ONNX path: models with HorizonNet's I/O exported from torch, run by the stage."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import torch.nn as nn
from layout_helpers import json_corners_xz, pose_world_to_camera_xz, run_layout, yaw_pose
from shapely.geometry import Point, Polygon

from layoutnet.export import export_onnx
from layoutnet.inference import LayoutModel, resolve_providers
from runfs.errors import PanoError

torch.set_num_threads(2)


class SmallLayoutNet(nn.Module):
    """HorizonNet's contract in miniature: a strided conv encoder, features pooled over the
    height, a bidirectional LSTM over 64 column groups, 16 columns x 3 outputs per step."""

    def __init__(self):
        super().__init__()
        self.enc = nn.Sequential(
            nn.Conv2d(3, 8, 5, stride=4, padding=2),
            nn.ReLU(),
            nn.Conv2d(8, 16, 5, stride=4, padding=2),
            nn.ReLU(),
        )
        self.rnn = nn.LSTM(16, 16, batch_first=True, bidirectional=True)
        self.head = nn.Linear(32, 3 * 16)
        with torch.no_grad():  # HorizonNet's bias init: corners -1, ceiling -0.478, floor 0.425
            self.head.bias[:16].fill_(-1)
            self.head.bias[16:32].fill_(-0.478)
            self.head.bias[32:].fill_(0.425)

    def forward(self, x):
        f = self.enc(x).mean(dim=2).permute(0, 2, 1)  # [B, 64, 16]
        out, _ = self.rnn(f)
        out = self.head(out).view(x.shape[0], 64, 3, 16).permute(0, 2, 1, 3).reshape(x.shape[0], 3, 1024)
        return out[:, 1:], out[:, :1]


class ConstantLayout(nn.Module):
    """Returns fixed outputs (a scene's true boundaries) whatever the image."""

    def __init__(self, bon: np.ndarray, cor: np.ndarray):
        super().__init__()
        self.register_buffer("bon", torch.as_tensor(bon, dtype=torch.float32).reshape(1, 2, -1))
        self.register_buffer("cor", torch.as_tensor(cor, dtype=torch.float32).reshape(1, 1, -1))

    def forward(self, x):
        z = x.mean() * 0.0  # keeps the input in the graph
        return self.bon + z, self.cor + z


class ColumnMeanLayout(nn.Module):
    """Per-column outputs from the column's mean colour: equivariant to flips and rolls."""

    def forward(self, x):
        m = x.mean(dim=(1, 2)).unsqueeze(1)  # [B,1,1024]
        return torch.cat([-(0.3 + 0.4 * m), 0.2 + 0.5 * m], dim=1), 4.0 * m - 2.0


@pytest.fixture(scope="module")
def small_onnx(tmp_path_factory) -> tuple[Path, float]:
    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("models") / "small.onnx"
    diff = export_onnx(SmallLayoutNet(), path)
    return path, diff


def _scene(root: Path, n: int = 2, size: int = 64) -> Path:
    (root / "images").mkdir(parents=True)
    views = []
    rng = np.random.default_rng(1)
    for i in range(n):
        cv2.imwrite(
            str(root / "images" / f"v{i}.png"), rng.integers(0, 255, (size, 2 * size, 3), dtype=np.uint8)
        )
        views.append(
            {
                "name": f"v{i}",
                "image": f"images/v{i}.png",
                "pose": yaw_pose(0.5 * i, (i, -1.5, 0)),
                "camera_height": 1.5,
                "split": "train" if i == 0 else "test",
            }
        )
    (root / "scene.json").write_text(json.dumps({"views": views}))
    return root


def test_small_model_exports_and_runs_end_to_end(tmp_path, small_onnx):
    path, diff = small_onnx
    assert diff < 1e-4
    root = _scene(tmp_path / "scene")
    for tta in (False, True):
        out, warnings = run_layout(root, tmp_path / f"out{tta}", model=path, tta=tta, splits="all")
        assert out.model == str(path)
        assert [v.view for v in out.views] == ["v0", "v1"] and [v.split for v in out.views] == [
            "train",
            "test",
        ]
        for v in out.views:
            assert v.source == "model"
            poly = Polygon(v.floor_polygon)
            assert poly.is_valid and poly.contains(Point(0, 0)) and poly.exterior.is_ccw
            assert np.load(tmp_path / f"out{tta}" / v.boundaries).shape == (2, 128)
            raw = np.load(tmp_path / f"out{tta}" / v.raw_boundaries)
            assert raw.shape == (2, 1024) and (raw[0] > 0).all() and (raw[1] < 0).all()
            conf = np.load(tmp_path / f"out{tta}" / v.confidence)
            assert conf.shape == (128,) and conf.min() >= 0 and conf.max() <= 1


def test_tta_undoes_flips_and_rolls(tmp_path):
    path = tmp_path / "colmean.onnx"
    export_onnx(ColumnMeanLayout(), path)
    model = LayoutModel(path)
    rgb = np.random.default_rng(0).uniform(0, 1, (512, 1024, 3)).astype(np.float32)
    b0, c0 = model.predict(rgb, tta=False)
    b1, c1 = model.predict(rgb, tta=True)
    np.testing.assert_allclose(b1, b0, atol=1e-6)
    np.testing.assert_allclose(c1, c0, atol=1e-6)
    m = rgb.mean(axis=(0, 2))
    np.testing.assert_allclose(b0[0], 0.3 + 0.4 * m, atol=1e-5)  # bon = -latitude
    np.testing.assert_allclose(c0, 1 / (1 + np.exp(-(4 * m - 2))), atol=1e-5)


def _corner_logits(cols: np.ndarray, width: int = 1024) -> np.ndarray:
    c = np.arange(width)[:, None]
    d = np.abs(c - cols[None])
    p = 0.96 ** np.minimum(d, width - d).min(axis=1)
    p = np.clip(p, 1e-4, 1 - 1e-4)
    return np.log(p / (1 - p))


@pytest.mark.parametrize("preset", ["cuboid", "l-shape"])
def test_true_boundary_model_through_the_whole_post_processing(tmp_path, preset):
    """An ONNX model that outputs a simulated view's true boundaries (and corner logits at its
    true corners): the stage must give back the room to 1 cm."""
    simulate = pytest.importorskip("simulate", reason="simulate/ not available yet")
    root = tmp_path / preset
    simulate.generate_scene(
        root, preset=preset, views=1, test_views=0, height=512, seed=3, effects="none", aa_samples=1
    )
    view = json.loads((root / "scene.json").read_text())["views"][0]
    plan = json.loads((root / "gt" / "floor_plan.json").read_text())
    gt = np.load(root / "gt" / "layout" / f"{view['name']}.npy").astype(np.float64)
    data = json.loads((root / "gt" / "layout" / f"{view['name']}.json").read_text())
    cols = np.unique(np.asarray(data["uv"])[::2, 0] * 1024)
    path = tmp_path / "truth.onnx"
    assert export_onnx(ConstantLayout(-gt, _corner_logits(cols)), path) < 1e-4
    # The model ignores the image and answers in the view's own frame: no alignment.
    out, _ = run_layout(root, tmp_path / "out", model=path, align="off")
    lay = out.view(view["name"])
    assert lay.source == "model" and lay.method == "manhattan" and lay.alignment is None
    ceiling = -plan["rooms"][0]["ceiling_y"]
    assert abs(lay.camera_height + lay.ceiling_distance - ceiling) < 0.01
    fitted = np.asarray(lay.floor_polygon)
    room = pose_world_to_camera_xz(plan["rooms"][0]["polygon"], view["pose"])
    vis = json_corners_xz(data, 1024, 512, view["camera_height"])
    seen_room = vis[np.linalg.norm(vis[:, None] - room[None], axis=2).min(axis=1) < 1e-6]
    assert np.linalg.norm(seen_room[:, None] - fitted[None], axis=2).min(axis=1).max() < 0.01
    assert Polygon(fitted).difference(Polygon(room)).area < 0.01
    conf = np.load(tmp_path / "out" / lay.confidence)
    assert np.median(conf) > 0.99


def _export_raw(module: nn.Module, path: Path, shape=(1, 3, 512, 1024), names=("bon", "cor")) -> Path:
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the legacy exporter's deprecation notes
        torch.onnx.export(
            module,
            (torch.rand(*shape),),
            str(path),
            dynamo=False,
            opset_version=17,
            input_names=["x"],
            output_names=list(names),
        )
    return path


def test_contract_errors_name_the_file_and_what_was_expected(tmp_path):
    cases = {
        "short.onnx": _export_raw(ConstantLayout(np.zeros((2, 512)), np.zeros(512)), tmp_path / "short.onnx"),
        "names.onnx": _export_raw(ColumnMeanLayout(), tmp_path / "names.onnx", names=("a", "b")),
        "input.onnx": _export_raw(ColumnMeanLayout(), tmp_path / "input.onnx", shape=(1, 3, 256, 512)),
    }
    for name, path in cases.items():
        with pytest.raises(PanoError) as ei:
            LayoutModel(path)
        msg = str(ei.value)
        assert msg.startswith(str(path)) and "\n" not in msg, name
        assert "expected one float32 input [1,3,512,1024] and outputs bon [1,2,1024], cor [1,1,1024]" in msg
    (tmp_path / "junk.onnx").write_bytes(b"\x00not an onnx model")
    with pytest.raises(PanoError, match="not a loadable ONNX model"):
        LayoutModel(tmp_path / "junk.onnx")
    with pytest.raises(PanoError, match="does not exist"):
        LayoutModel(tmp_path / "none.onnx")
    with pytest.raises(PanoError, match="not available"):
        resolve_providers(["NoSuchExecutionProvider"])
    assert resolve_providers()[-1] == "CPUExecutionProvider"


def test_stage_rejects_a_model_that_does_not_fit(tmp_path):
    root = _scene(tmp_path / "scene", n=1)
    bad = _export_raw(ColumnMeanLayout(), tmp_path / "bad.onnx", names=("bon", "corners"))
    with pytest.raises(PanoError, match="bad.onnx: model does not fit HorizonNet's contract"):
        run_layout(root, tmp_path / "out", model=bad)


def test_nan_model_output_is_a_one_line_error(tmp_path):
    root = _scene(tmp_path / "scene", n=1)
    bon = np.full((2, 1024), np.nan)
    path = _export_raw(ConstantLayout(bon, np.zeros(1024)), tmp_path / "nan.onnx")
    with pytest.raises(PanoError, match="nan.onnx: view v0: unusable output: boundaries contain NaN"):
        run_layout(root, tmp_path / "out", model=path)


def test_splits_train_leaves_test_views_out(tmp_path, small_onnx):
    root = _scene(tmp_path / "scene")
    out, _ = run_layout(root, tmp_path / "out", model=small_onnx[0], splits="train", wall_source="ceiling")
    assert [v.view for v in out.views] == ["v0"] and out.train_views() == out.views
