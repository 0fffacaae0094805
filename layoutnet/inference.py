"""HorizonNet-compatible ONNX inference with onnxruntime.

The contract (HorizonNet's): one float32 input [1,3,512,1024], RGB in [0,1]
(the model normalises internally); outputs `bon` [1,2,1024], the ceiling and
floor boundaries in radians measured downward (bon = -latitude), and `cor`
[1,1,1024], corner logits.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from runfs.errors import PanoError, one_line

INPUT_SHAPE = (1, 3, 512, 1024)
OUTPUT_SHAPES = {"bon": (1, 2, 1024), "cor": (1, 1, 1024)}
CONTRACT = "one float32 input [1,3,512,1024] and outputs bon [1,2,1024], cor [1,1,1024]"

#: Test-time augmentation: horizontal flip and circular rolls by these fractions of the width.
TTA_ROLLS = (0.25, 0.5, 0.75)

__all__ = ["LayoutModel", "resolve_providers", "check_contract", "INPUT_SHAPE", "OUTPUT_SHAPES"]


def resolve_providers(requested: Sequence[str] | None = None) -> list[str]:
    """onnxruntime providers: the requested ones that exist, or CUDA when present, then CPU."""
    from models.onnxrt import onnxruntime

    available = onnxruntime().get_available_providers()
    if requested:
        missing = [p for p in requested if p not in available]
        if missing:
            raise PanoError(
                "layout.providers", f"{', '.join(missing)} not available here (have: {', '.join(available)})"
            )
        return list(requested)
    chosen = [p for p in ("CUDAExecutionProvider",) if p in available]
    return chosen + ["CPUExecutionProvider"]


def _fits(shape, expected) -> bool:
    # Symbolic (str) or unknown (None) dimensions fit anything.
    return len(shape) == len(expected) and all(
        not isinstance(d, int) or d == e for d, e in zip(shape, expected)
    )


def _shape_text(shape) -> str:
    return "[" + ",".join(str(d) for d in shape) + "]"


def check_contract(session, path: Path) -> str:
    """Raise PanoError naming the model file unless it fits HorizonNet's I/O; returns the input name."""
    ins = session.get_inputs()
    outs = {o.name: o for o in session.get_outputs()}
    got = (
        ", ".join(f"input {i.name}{_shape_text(i.shape)}" for i in ins)
        + "; "
        + ", ".join(f"output {o.name}{_shape_text(o.shape)}" for o in outs.values())
    )
    ok = len(ins) == 1 and _fits(ins[0].shape, INPUT_SHAPE) and ins[0].type == "tensor(float)"
    for name, shape in OUTPUT_SHAPES.items():
        ok = ok and name in outs and _fits(outs[name].shape, shape)
    if not ok:
        raise PanoError(path, f"model does not fit HorizonNet's contract: expected {CONTRACT}; got {got}")
    return ins[0].name


class LayoutModel:
    """A loaded, checked HorizonNet-compatible ONNX model."""

    def __init__(self, path: str | Path, providers: Sequence[str] | None = None, threads: int | None = None):
        from models.onnxrt import inference_session, onnxruntime

        ort = onnxruntime()
        self.path = Path(path)
        if not self.path.is_file():
            raise PanoError(self.path, "layout model file does not exist")
        opts = ort.SessionOptions()
        if threads:
            opts.intra_op_num_threads = threads
        opts.log_severity_level = 3
        try:
            self.session = inference_session(self.path, opts, resolve_providers(providers))
        except PanoError:
            raise
        except Exception as e:  # onnxruntime raises its own exception types
            raise PanoError(self.path, f"not a loadable ONNX model: {one_line(e, 200)}") from None
        self.input_name = check_contract(self.session, self.path)

    def _run(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        bon, cor = self.session.run(["bon", "cor"], {self.input_name: x})
        return np.asarray(bon, dtype=np.float64)[0], np.asarray(cor, dtype=np.float64)[0, 0]

    def predict(self, rgb: np.ndarray, tta: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """rgb [512,1024,3] float in [0,1] → (boundaries [2,1024] latitudes, corner probabilities [1024]).
        With tta, the outputs of the flipped and rolled panoramas are undone and averaged
        (probabilities after the sigmoid, as HorizonNet's inference does)."""
        x = np.ascontiguousarray(np.asarray(rgb, dtype=np.float32).transpose(2, 0, 1)[None])
        if x.shape != INPUT_SHAPE:
            raise ValueError(
                f"expected an image of {INPUT_SHAPE[2]}x{INPUT_SHAPE[3]}, got {x.shape[2]}x{x.shape[3]}"
            )
        w = x.shape[-1]
        bons, cors = [], []
        augs: list[tuple[str, int]] = [("id", 0)]
        if tta:
            augs += [("flip", 0)] + [("roll", int(round(f * w))) for f in TTA_ROLLS]
        for kind, shift in augs:
            xa = x[..., ::-1] if kind == "flip" else np.roll(x, shift, axis=-1) if kind == "roll" else x
            bon, cor = self._run(np.ascontiguousarray(xa))
            if kind == "flip":
                bon, cor = bon[:, ::-1], cor[::-1]
            elif kind == "roll":
                bon, cor = np.roll(bon, -shift, axis=-1), np.roll(cor, -shift)
            bons.append(bon)
            cors.append(1.0 / (1.0 + np.exp(-cor)))
        bon = np.mean(bons, axis=0)
        return -bon, np.mean(cors, axis=0)
