"""Export a HorizonNet(-compatible) torch module to ONNX and check it.

Legacy TorchScript exporter (`dynamo=False`), batch 1, fixed 512x1024, input
`x`, outputs `bon` [1,2,1024] and `cor` [1,1,1024]; onnxruntime must agree
with torch to < 1e-4 (max absolute difference) on a random panorama.
"""

from __future__ import annotations

import warnings
from collections import OrderedDict
from pathlib import Path

import numpy as np
import torch

from layoutnet.inference import INPUT_SHAPE
from runfs.checkpoints import load_weights
from runfs.errors import PanoError

MAX_DIFF = 1e-4

__all__ = ["export_onnx", "load_checkpoint", "export_checkpoint", "MAX_DIFF"]


def export_onnx(
    module: torch.nn.Module, out: str | Path, opset: int = 17, seed: int = 0, check: bool = True
) -> float:
    """Export `module` (x [1,3,512,1024] -> (bon, cor)) to `out`; returns the max
    |onnxruntime - torch| over both outputs, raising when it is >= MAX_DIFF."""
    if opset < 17:
        raise PanoError("--opset", f"opset {opset} is too old: use 17 or newer")
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    module = module.eval()
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(*INPUT_SHAPE, generator=g)
    with torch.no_grad(), warnings.catch_warnings():
        # The tracer's notes on the fixed-size check and LSTM batch size: the export is batch 1, fixed size.
        warnings.simplefilter("ignore")
        ref_bon, ref_cor = module(x)
        torch.onnx.export(
            module,
            (x,),
            str(out),
            dynamo=False,
            opset_version=opset,
            input_names=["x"],
            output_names=["bon", "cor"],
            do_constant_folding=True,
        )
    if not check:
        return float("nan")
    from layoutnet.inference import LayoutModel

    model = LayoutModel(out, providers=["CPUExecutionProvider"])  # also checks names and shapes
    bon, cor = model.session.run(["bon", "cor"], {model.input_name: x.numpy()})
    diff = max(float(np.abs(bon - ref_bon.numpy()).max()), float(np.abs(cor - ref_cor.numpy()).max()))
    if not diff < MAX_DIFF:
        raise PanoError(out, f"onnxruntime and torch disagree by {diff:.3g} (limit {MAX_DIFF:g})")
    return diff


def load_checkpoint(path: str | Path) -> torch.nn.Module:
    """A HorizonNet checkpoint as saved by its train.py: {'state_dict', 'kwargs':
    {'backbone', 'use_rnn'}, 'args'}; a bare state dict and DataParallel's
    'module.' prefixes are accepted too."""
    from layoutnet.model import build_from_state_dict

    path = Path(path)
    if not path.is_file():
        raise PanoError(path, "checkpoint file does not exist")
    ckpt = load_weights(path)  # HorizonNet checkpoints hold only tensors, dicts and plain values
    if not isinstance(ckpt, dict):
        raise PanoError(path, f"expected a dict with 'state_dict', got {type(ckpt).__name__}")
    sd = ckpt.get("state_dict", ckpt)
    kwargs = ckpt.get("kwargs") if isinstance(ckpt.get("kwargs"), dict) else {}
    if not isinstance(sd, dict) or not all(isinstance(v, torch.Tensor) for v in sd.values()):
        raise PanoError(path, "the 'state_dict' entry is not a dict of tensors")
    sd = OrderedDict((k.removeprefix("module."), v) for k, v in sd.items())
    if not any(k.startswith("feature_extractor.encoder.") for k in sd):
        raise PanoError(path, "not a HorizonNet state dict (no feature_extractor.encoder.* tensors)")
    try:
        return build_from_state_dict(sd, kwargs)
    except (RuntimeError, ValueError, KeyError) as e:
        msg = " ".join(str(e).split())
        raise PanoError(path, f"does not load into HorizonNet: {msg[:300]}") from None


def export_checkpoint(checkpoint: str | Path, out: str | Path, opset: int = 17) -> float:
    """Checkpoint → ONNX, checked; returns the max onnxruntime-torch difference."""
    if opset < 17:  # before the (slow) load
        raise PanoError("--opset", f"opset {opset} is too old: use 17 or newer")
    with torch.no_grad():  # a global switch would leak into the caller's process
        return export_onnx(load_checkpoint(checkpoint), out, opset=opset)
