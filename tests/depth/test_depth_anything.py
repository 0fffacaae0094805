"""Depth Anything V2 Small written here: the official checkpoint's state-dict layout, DINOv2's
position-embedding interpolation, the strict checkpoint load, the ONNX export against torch, and
the exported model through the depth stage (`depth.model: X.pth`, exported on first use).

The expected keys and shapes below are written out from the official repository
(DepthAnything/Depth-Anything-V2: depth_anything_v2/dpt.py, dinov2.py, util/blocks.py; the
`vits` config features=64, out_channels=[48, 96, 192, 384]), not read from our module.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from depthnet.depth_anything import (
    MAX_DIFF,
    DepthAnythingV2,
    _Exported,
    export_module,
    load_checkpoint,
    normalize,
    onnx_vs_torch,
)
from runfs.errors import PanoError


def official_vits_shapes() -> dict[str, tuple[int, ...]]:
    """Every tensor of depth_anything_v2_vits.pth with its shape."""
    d, hidden, feat = 384, 1536, 64
    oc = (48, 96, 192, 384)
    s = {
        "pretrained.cls_token": (1, 1, d),
        "pretrained.pos_embed": (1, 37 * 37 + 1, d),  # 518 / 14 = 37 patches a side, plus the class token
        "pretrained.mask_token": (1, d),
        "pretrained.patch_embed.proj.weight": (d, 3, 14, 14),
        "pretrained.patch_embed.proj.bias": (d,),
        "pretrained.norm.weight": (d,),
        "pretrained.norm.bias": (d,),
    }
    for i in range(12):
        b = f"pretrained.blocks.{i}."
        s |= {
            b + "norm1.weight": (d,), b + "norm1.bias": (d,),
            b + "attn.qkv.weight": (3 * d, d), b + "attn.qkv.bias": (3 * d,),
            b + "attn.proj.weight": (d, d), b + "attn.proj.bias": (d,),
            b + "ls1.gamma": (d,),
            b + "norm2.weight": (d,), b + "norm2.bias": (d,),
            b + "mlp.fc1.weight": (hidden, d), b + "mlp.fc1.bias": (hidden,),
            b + "mlp.fc2.weight": (d, hidden), b + "mlp.fc2.bias": (d,),
            b + "ls2.gamma": (d,),
        }
    h = "depth_head."
    for i, c in enumerate(oc):
        s |= {f"{h}projects.{i}.weight": (c, d, 1, 1), f"{h}projects.{i}.bias": (c,)}
    s |= {
        h + "resize_layers.0.weight": (48, 48, 4, 4), h + "resize_layers.0.bias": (48,),  # ConvTranspose2d
        h + "resize_layers.1.weight": (96, 96, 2, 2), h + "resize_layers.1.bias": (96,),  # ConvTranspose2d
        h + "resize_layers.3.weight": (384, 384, 3, 3), h + "resize_layers.3.bias": (384,),  # stride-2 conv
    }
    for i, c in enumerate(oc, start=1):
        s[f"{h}scratch.layer{i}_rn.weight"] = (feat, c, 3, 3)  # no bias
    for k in range(1, 5):
        r = f"{h}scratch.refinenet{k}."
        s |= {r + "out_conv.weight": (feat, feat, 1, 1), r + "out_conv.bias": (feat,)}
        for unit in ("resConfUnit1", "resConfUnit2"):
            for conv in ("conv1", "conv2"):
                s |= {f"{r}{unit}.{conv}.weight": (feat, feat, 3, 3), f"{r}{unit}.{conv}.bias": (feat,)}
    s |= {
        h + "scratch.output_conv1.weight": (32, feat, 3, 3), h + "scratch.output_conv1.bias": (32,),
        h + "scratch.output_conv2.0.weight": (32, 32, 3, 3), h + "scratch.output_conv2.0.bias": (32,),
        h + "scratch.output_conv2.2.weight": (1, 32, 1, 1), h + "scratch.output_conv2.2.bias": (1,),
    }
    return s


def random_small(seed: int = 0) -> DepthAnythingV2:
    """ViT-S with random weights, its last layer set so the disparity is positive, about 5 +- 2
    (a trained model's range), so an export check cannot pass on a map the final ReLU zeroed."""
    torch.manual_seed(seed)
    model = DepthAnythingV2().eval()
    last = model.depth_head.scratch.output_conv2[2]
    with torch.no_grad():
        last.weight.mul_(40.0)
        last.bias.fill_(5.0)
    return model


def test_state_dict_has_the_official_keys_and_shapes():
    sd = DepthAnythingV2().state_dict()
    want = official_vits_shapes()
    assert sorted(sd) == sorted(want)
    assert {k: tuple(v.shape) for k, v in sd.items()} == want
    assert sum(v.numel() for v in sd.values()) == sum(math.prod(s) for s in want.values()) == 24_785_089


def _official_pos_embed(pos: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """DINOv2's interpolate_pos_encoding (no register tokens, offset 0.1), for comparison."""
    n = pos.shape[1] - 1
    rows, cols = height // 14, width // 14
    if rows * cols == n and height == width:
        return pos
    side = int(math.sqrt(n))
    grid = pos[:, 1:].reshape(1, side, side, -1).permute(0, 3, 1, 2)
    grid = F.interpolate(grid, scale_factor=((rows + 0.1) / side, (cols + 0.1) / side), mode="bicubic",
                         antialias=False)
    assert grid.shape[-2:] == (rows, cols)
    return torch.cat([pos[:, :1], grid.permute(0, 2, 3, 1).reshape(1, rows * cols, -1)], 1)


@pytest.mark.parametrize(
    "hw", [(518, 518), (518, 1036), (98, 140), (28, 28), (700, 700), (518, 532), (14, 28)]
)
def test_position_embedding_equals_torch_bicubic_with_the_official_scale(hw):
    enc = DepthAnythingV2().pretrained
    with torch.no_grad():
        ours = enc.position_embedding(*hw)
        ref = _official_pos_embed(enc.pos_embed, *hw)
    assert ours.shape == ref.shape
    assert (ours - ref).abs().max() < 1e-5


def test_forward_shape_and_input_normalisation():
    model = random_small()
    rgb = torch.rand(2, 3, 42, 70)
    with torch.no_grad():
        out = model(normalize(rgb))
    assert out.shape == (2, 42, 70) and (out >= 0).all() and out.std() > 0.1
    x = normalize(torch.ones(1, 3, 1, 1))
    mean, std = np.array([0.485, 0.456, 0.406]), np.array([0.229, 0.224, 0.225])
    assert np.allclose(x.flatten().numpy(), (1 - mean) / std)


@pytest.fixture(scope="module")
def official_checkpoint(tmp_path_factory):
    """A checkpoint in the official layout (a bare state dict saved by torch.save), random weights."""
    model = random_small(seed=1)
    path = tmp_path_factory.mktemp("da2") / "depth_anything_v2_vits.pth"
    torch.save(model.state_dict(), path)
    return path, model


def test_checkpoint_loads_strictly_and_bad_ones_are_refused(official_checkpoint, tmp_path):
    path, model = official_checkpoint
    loaded = load_checkpoint(path)
    x = normalize(torch.rand(1, 3, 28, 42))
    with torch.no_grad():
        assert torch.equal(loaded(x), model(x))
    sd = torch.load(path, weights_only=True)
    torch.save({"state_dict": {f"module.{k}": v for k, v in sd.items()}}, tmp_path / "wrapped.pth")
    with torch.no_grad():
        assert torch.equal(load_checkpoint(tmp_path / "wrapped.pth")(x), model(x))
    cases = {
        "missing.pth": {k: v for k, v in sd.items() if k != "depth_head.scratch.output_conv1.bias"},
        "extra.pth": {**sd, "depth_head.readout_projects.0.0.weight": torch.zeros(384, 768)},
        "shape.pth": {**sd, "depth_head.projects.0.weight": torch.zeros(49, 384, 1, 1)},
        "other.pth": {"conv.weight": torch.zeros(3, 3)},
        "list.pth": [1, 2, 3],
    }
    for name, obj in cases.items():
        torch.save(obj, tmp_path / name)
        with pytest.raises(PanoError) as e:
            load_checkpoint(tmp_path / name)
        assert "\n" not in str(e.value) and name in str(e.value)
    (tmp_path / "junk.pth").write_bytes(b"not a checkpoint")
    with pytest.raises(PanoError, match="not a readable PyTorch checkpoint"):
        load_checkpoint(tmp_path / "junk.pth")


@pytest.fixture(scope="module")
def exported(official_checkpoint, tmp_path_factory):
    """The checkpoint through `depth.model: X.pth` resolution: exported once into the model cache."""
    from models import resolve_model

    path, model = official_checkpoint
    onnx_path = resolve_model(path, "depth")
    return onnx_path, model


def test_onnx_export_matches_torch_at_any_size(exported):
    onnx_path, model = exported
    assert onnx_path.suffix == ".onnx" and "exported" in onnx_path.parts
    module = _Exported(model)
    g = torch.Generator().manual_seed(3)
    for shape in [(1, 3, 56, 84), (2, 3, 70, 42), (1, 3, 154, 154)]:
        x = normalize(torch.rand(*shape, generator=g))
        with torch.no_grad():
            assert module(x).abs().max() > 1.0  # a real signal, not the ReLU's zeros
        assert onnx_vs_torch(module, onnx_path, x) <= MAX_DIFF


def test_export_at_and_off_the_native_grid(tmp_path):
    """At the training size (here a 3 x 3 grid, 42 px) the stored embedding is used as is; off it,
    interpolated. The exported graph must take both paths from the input size alone."""
    import depthnet.depth_anything as da

    cfg = da.Config("tiny", embed_dim=32, depth=4, num_heads=2, features=8, out_channels=(4, 8, 16, 32),
                    layers=(0, 1, 2, 3), pretrain_size=42)
    torch.manual_seed(2)
    model = DepthAnythingV2(cfg).eval()
    with torch.no_grad():
        model.depth_head.scratch.output_conv2[2].weight.mul_(40.0)  # outputs of a few units
        model.depth_head.scratch.output_conv2[2].bias.fill_(5.0)
        assert torch.equal(model.pretrained.position_embedding(42, 42), model.pretrained.pos_embed)
        assert not torch.allclose(model.pretrained.position_embedding(42, 56)[:, :10],
                                  model.pretrained.pos_embed[:, :10])
    out = tmp_path / "tiny.onnx"
    export_module(model, out, check_size=(28, 56))
    module = _Exported(model)
    for shape in [(1, 3, 42, 42), (1, 3, 42, 56), (1, 3, 56, 56), (1, 3, 28, 28)]:
        assert onnx_vs_torch(module, out, normalize(torch.rand(*shape))) <= 1e-5


def test_export_refuses_a_model_it_cannot_reproduce(tmp_path, monkeypatch):
    import depthnet.depth_anything as da

    monkeypatch.setattr(da, "onnx_vs_torch", lambda *a, **k: 1e-2)
    out = tmp_path / "bad.onnx"
    tiny = da.Config("tiny", embed_dim=32, depth=4, num_heads=2, features=8, out_channels=(4, 8, 16, 32),
                     layers=(0, 1, 2, 3))
    with pytest.raises(PanoError, match="disagree"):
        export_module(DepthAnythingV2(tiny), out, check_size=(28, 28))
    assert not out.exists() and not list(tmp_path.iterdir())  # nothing half-written left behind


def test_export_depth_model_command_reports_bad_input(tmp_path, capsys):
    from tests.clitools import invoke

    code, _, err = invoke(["export-depth-model", tmp_path / "none.pth", tmp_path / "x.onnx"], capsys)
    assert code == 2 and err.startswith("error:") and "does not exist" in err
    assert len(err.strip().splitlines()) == 1
    (tmp_path / "a.pth").write_bytes(b"junk")
    args = ["export-depth-model", tmp_path / "a.pth", tmp_path / "x.onnx", "--opset", "13"]
    code, _, err = invoke(args, capsys)
    assert code == 2 and "opset 13 is too old" in err


def test_exported_model_runs_in_the_depth_stage_under_its_recorded_contract(dk, exported, tmp_path):
    """No contract settings: the ONNX metadata says cube faces, ImageNet input, disparity."""
    onnx_path, model = exported
    scene = dk.make_encoded_scene(tmp_path / "s", "cuboid", views=1, height=32, seed=4)
    result, maps, _ = dk.run_depth(scene, tmp_path, model=str(onnx_path), face_size=28)
    assert result.network == "Depth Anything V2 (vits)"
    assert result.contract["projection"] == "cubemap" and result.contract["normalization"] == "imagenet"
    (view,) = result.views
    assert view.kind == "disparity" and view.depth_model == "affine inverse depth"
    assert view.model_input == (28, 28) and len(view.face_scales) == 6
    m = maps[view.view]
    assert m.shape == (32, 64) and np.isfinite(m).mean() > 0.9
    # The settings still win over the metadata.
    result, _, _ = dk.run_depth(scene, tmp_path, model=str(onnx_path), projection="equirect", max_height=28)
    assert result.views[0].model_input == (28, 56) and result.views[0].face_scales is None
