"""train.device: validation, the CUDA-less error, checkpoints that move across devices, and a
few iterations through the `cuda` splatting backend (the Triton interpreter without a GPU)."""

from __future__ import annotations

import pytest
import torch
from pydantic import ValidationError
from train_helpers import camera_positions, load_views, rooms, small_config

from gaussians.init import random_points
from gaussians.trainer import Trainer
from runfs.errors import PanoError
from stages.train import Params, resolve_device


def _init(root, n=300):
    return random_points(n, 0, rooms=rooms(root), camera_positions=camera_positions(root), sh_degree=1)


def test_device_param_is_validated():
    assert Params().device == "auto"
    assert Params(device="cpu").device == "cpu"
    with pytest.raises(ValidationError):
        Params(device="gpu")
    assert resolve_device("cpu", "train.device") == "cpu"
    assert resolve_device("auto", "train.device") == ("cuda" if torch.cuda.is_available() else "cpu")


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the machine without CUDA")
def test_cuda_without_cuda_is_a_one_line_input_error():
    with pytest.raises(PanoError, match="no CUDA device") as e:
        resolve_device("cuda", "train.device")
    assert "\n" not in str(e.value)


def test_device_is_not_part_of_the_fingerprint():
    assert small_config(device="cpu").fingerprint() == small_config(device="cuda").fingerprint()


@pytest.mark.cuda
def test_checkpoint_is_device_neutral_and_loads_onto_the_trainer_device(tiny_room, tmp_path, monkeypatch):
    views = load_views(tiny_room)
    tr = Trainer(_init(tiny_room), views, small_config(iterations=6, densify_from=100))
    tr.train(until=3)
    ckpt = tmp_path / "ckpt.pt"
    tr.save_checkpoint(ckpt)
    state = torch.load(ckpt, weights_only=True)
    tensors = [v for v in state["gaussians"].values()] + list(state["opt"]["exp_avg"].values())
    assert tensors and all(t.device.type == "cpu" for t in tensors)

    # a trainer on another device: the loader reads to the CPU (map_location), validates, then moves
    target = "cuda" if torch.cuda.is_available() else "meta"
    seen = {}
    real_load = torch.load

    def spy(*a, **kw):
        seen["map_location"] = kw.get("map_location")
        return real_load(*a, **kw)

    monkeypatch.setattr(torch, "load", spy)
    other = Trainer(_init(tiny_room), views, small_config(iterations=6, densify_from=100, device=target))
    other.load_checkpoint(ckpt)
    assert seen["map_location"] == "cpu"
    assert other.iteration == 3
    assert other.g.means.device.type == target
    assert all(m.device.type == target for m in other.opt.exp_avg.values())
    assert other.stats.grad_accum.device.type == target
    if target == "cuda":
        torch.testing.assert_close(other.g.means.cpu(), tr.g.means)


@pytest.mark.cuda
def test_a_few_iterations_through_the_cuda_backend_match_cpp(tiny_room, monkeypatch):
    """Three optimiser steps with the Triton kernels (interpreted without a GPU) against the C++
    kernel, over a grey background. On CPU tensors too the step takes every path a GPU takes (the
    fused loss and the PSNR from its sums, the background composited in the raster kernels, the
    densification statistics' kernel), so the losses and PSNRs compared are the GPU's."""
    pytest.importorskip("triton")
    from gaussians import losses as loss_module
    from splatting import devices, raster_triton

    device = "cuda" if torch.cuda.is_available() else "cpu"
    if raster_triton.unavailable_reason(torch.device(device)) is not None:
        pytest.fail(raster_triton.unavailable_reason(torch.device(device)))
    # 16x32 (two 16-pixel tiles) and 120 Gaussians: the interpreter's time grows with tiles x pairs
    views = load_views(tiny_room, height=16)
    runs = {}
    for backend in ("cpp", "cuda"):
        if backend == "cuda":
            monkeypatch.setattr(devices, "KERNELS_ON_CPU", True)
            monkeypatch.setattr(loss_module, "_cpu_kernels", lambda x: None)
        cfg = small_config(iterations=3, densify_from=100, backend=backend, background=(0.3, 0.4, 0.5),
                           device=device if backend == "cuda" else "cpu")
        tr = Trainer(_init(tiny_room, 120), views, cfg)
        losses, psnrs = [], []
        tr.train(on_step=lambda t, info: (losses.append(float(info["loss"])), psnrs.append(float(info["psnr"]))))
        runs[backend] = (losses, psnrs, tr.g.means.detach().cpu())
    assert runs["cuda"][0] == pytest.approx(runs["cpp"][0], rel=1e-4)
    assert runs["cuda"][1] == pytest.approx(runs["cpp"][1], abs=1e-3)
    torch.testing.assert_close(runs["cuda"][2], runs["cpp"][2], atol=1e-5, rtol=1e-4)
