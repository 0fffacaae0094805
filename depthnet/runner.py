"""Run an ONNX depth network under a declared contract (onnxruntime; CUDA if available, else CPU).

The contract says what the network expects and returns, so the same runner
serves the models users actually have:

- 360° depth networks: a fixed equirectangular input (e.g. 512x1024), [0,1]
  input, metric depth output (`output="metric"`).
- Depth Anything exports: dynamic sides that must be multiples of 14,
  ImageNet normalisation, relative disparity output [1,H,W]
  (`normalization="imagenet"`, `multiple_of=14`, `output="disparity"`).
- Any perspective network: run on the six cube faces of the panorama
  (`projection="cubemap"`, see depthnet/cubemap.py).

Input: float32 NCHW RGB. Output: [1,H',W'], [1,1,H',W'] or [H',W'] with the
input's aspect ratio (the output may be smaller, e.g. a stride-2 decoder).
Shapes are checked when the model loads and again on its first output; any
mismatch is a one-line PanoError naming the model file.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from runfs.errors import PanoError, one_line

IMAGENET_MEAN = np.array([0.485, 0.456, 0.406], dtype=np.float32)
IMAGENET_STD = np.array([0.229, 0.224, 0.225], dtype=np.float32)
# ONNX metadata keys pano-pipe's exporters write (depthnet/depth_anything.py): the contract, the network.
CONTRACT_METADATA_KEY = "pano_pipe.depth_contract"
MODEL_METADATA_KEY = "pano_pipe.depth_model"


class DepthContract(BaseModel):
    """What an ONNX depth model takes and gives (the depth stage's model parameters)."""

    model_config = ConfigDict(extra="forbid")

    output: Literal["metric", "relative", "disparity"] = Field(
        default="metric",
        description="metric: metres; relative: depth up to scale and shift; disparity: inverse depth up to "
        "scale and shift (Depth Anything).",
    )
    normalization: Literal["unit", "imagenet"] = Field(
        default="unit", description="unit: RGB in [0,1]; imagenet: (x - mean) / std after [0,1]."
    )
    input_size: tuple[int, int] | None = Field(
        default=None, description="(H, W) fed to the model; None: the model's static size, else derived."
    )
    multiple_of: int = Field(
        default=1, ge=1, description="Input sides must be multiples of this (14 for ViTs)."
    )
    max_height: int = Field(
        default=512, ge=8, description="Input height cap when the model's size is dynamic."
    )
    projection: Literal["equirect", "cubemap"] = Field(
        default="equirect",
        description="equirect: a 360° model; cubemap: a perspective model on six cube faces.",
    )
    face_size: int = Field(
        default=256, ge=8, description="Cube face side (px) when the model's size is dynamic."
    )
    face_fov_deg: float = Field(
        default=100.0,
        ge=90.0,
        lt=170.0,
        description="Cube face field of view; >90° overlaps neighbouring faces.",
    )
    perspective_axis: Literal["z", "ray"] = Field(
        default="z",
        description="A perspective model's depth is along the optical axis (z, usual) or the ray.",
    )


def write_metadata(onnx_path: str | Path, contract: dict, network: dict | None = None) -> None:
    """Record a depth contract (DepthContract fields) and what the network is in an ONNX file's
    metadata, so the depth stage runs it without settings."""
    import json

    import onnx

    DepthContract(**contract)  # refuse a contract the stage could not read back
    proto = onnx.load(str(onnx_path))
    entries = {CONTRACT_METADATA_KEY: json.dumps(contract)}
    if network is not None:
        entries[MODEL_METADATA_KEY] = json.dumps(network)
    kept = [e for e in proto.metadata_props if e.key not in entries]
    del proto.metadata_props[:]
    proto.metadata_props.extend(kept)
    for key, value in entries.items():
        entry = proto.metadata_props.add()
        entry.key, entry.value = key, value
    onnx.save(proto, str(onnx_path))


def _static(dim) -> int | None:
    return dim if isinstance(dim, int) and dim > 0 else None


def _round_to(x: float, m: int) -> int:
    return max(m, int(round(x / m)) * m)


class OnnxDepthModel:
    """An onnxruntime session with its contract; `predict(rgb)` returns the raw output map."""

    def __init__(
        self,
        path: str | Path,
        contract: DepthContract | None = None,
        threads: int = 2,
        providers: list[str] | None = None,
        overrides: dict | None = None,
    ):
        """`contract` given: used as is. Else the contract the model's metadata records (pano-pipe's
        exports write it, key `pano_pipe.depth_contract`), with `overrides` (the user's settings) on
        top, and DepthContract's defaults for the rest."""
        from models.onnxrt import inference_session, onnxruntime

        ort = onnxruntime()
        self.path = Path(path)
        if not self.path.is_file():
            raise PanoError(self.path, "depth model not found")
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = threads
        opts.inter_op_num_threads = 1
        opts.log_severity_level = 4  # errors reach the user as PanoError, not as log spam
        have = ort.get_available_providers()
        if providers is None:  # CUDA where this onnxruntime build has it, else CPU
            providers = [p for p in ("CUDAExecutionProvider", "CPUExecutionProvider") if p in have]
        elif missing := [p for p in providers if p not in have]:
            raise PanoError(self.path, f"onnxruntime providers {missing} not available here (have {have})")
        try:
            self.session = inference_session(self.path, opts, providers)
        except Exception as exc:  # onnxruntime raises its own types; the user needs one line
            raise PanoError(self.path, f"not a loadable ONNX model ({one_line(exc, 200)})") from None
        self.metadata = dict(self.session.get_modelmeta().custom_metadata_map)
        self.contract = contract if contract is not None else self._contract(overrides or {})
        c = self.contract
        inputs = self.session.get_inputs()
        if len(inputs) != 1:
            raise PanoError(self.path, f"depth model must take one input (an image), it takes {len(inputs)}")
        shape = list(inputs[0].shape)
        if len(shape) != 4:
            raise PanoError(self.path, f"model input must be NCHW (rank 4), got shape {shape}")
        if _static(shape[1]) not in (None, 3):
            raise PanoError(self.path, f"model input must have 3 channels (NCHW RGB), got shape {shape}")
        self.input_name = inputs[0].name
        self.static_hw = (_static(shape[2]), _static(shape[3]))
        m = c.multiple_of
        for side in self.static_hw:
            if side is not None and side % m:
                raise PanoError(self.path, f"model input side {side} is not a multiple of {m} (multiple_of)")
        if c.input_size is not None:
            ih, iw = c.input_size
            if ih % m or iw % m:
                raise PanoError(self.path, f"input_size {c.input_size} is not a multiple of {m}")
            for want, have in zip((ih, iw), self.static_hw, strict=True):
                if have is not None and have != want:
                    raise PanoError(
                        self.path,
                        f"model input is fixed at {shape}, input_size says {list(c.input_size)}",
                    )
        if c.projection == "equirect":
            h, w = self.static_hw
            if h is not None and w is not None and w != 2 * h:
                raise PanoError(
                    self.path,
                    f"model input {h}x{w} is not 2:1; a perspective model needs projection='cubemap'",
                )
        elif (
            self.static_hw[0] is not None
            and self.static_hw[1] is not None
            and self.static_hw[0] != self.static_hw[1]
        ):
            raise PanoError(self.path, f"cube faces are square; model input is fixed at {shape}")
        outputs = self.session.get_outputs()
        oshape = list(outputs[0].shape)
        if len(oshape) not in (2, 3, 4) or (len(oshape) >= 3 and _static(oshape[-3]) not in (None, 1)):
            raise PanoError(
                self.path, f"model output must be a depth map [1,H,W] or [1,1,H,W], got shape {oshape}"
            )
        self.output_name = outputs[0].name

    def _contract(self, overrides: dict) -> DepthContract:
        import json

        raw = self.metadata.get(CONTRACT_METADATA_KEY)
        recorded = {}
        if raw:
            try:
                recorded = json.loads(raw)
                DepthContract(**recorded)
            except (ValueError, TypeError) as e:
                msg = " ".join(str(e).split())[:200]
                raise PanoError(self.path, f"unreadable depth contract in the metadata: {msg}") from None
        return DepthContract(**{**recorded, **overrides})

    @property
    def description(self) -> dict:
        """What the exporter recorded about the network (`pano_pipe.depth_model`), or {}."""
        import json

        try:
            return json.loads(self.metadata.get(MODEL_METADATA_KEY, "{}"))
        except ValueError:
            return {}

    # -- sizes ---------------------------------------------------------------
    def input_hw(self, image_hw: tuple[int, int]) -> tuple[int, int]:
        """The (H, W) to feed for an equirectangular image of `image_hw`, or a cube face (square)."""
        c = self.contract
        sh, sw = self.static_hw
        if c.input_size is not None:
            return tuple(c.input_size)
        m = c.multiple_of
        if c.projection == "cubemap":
            s = sh or sw or _round_to(c.face_size, m)
            return s, s
        if sh is not None and sw is not None:
            return sh, sw
        h = sh or _round_to(min(image_hw[0], c.max_height), m)
        w = sw or _round_to(2 * h, m)
        return h, w

    # -- inference -------------------------------------------------------------
    def preprocess(self, rgb: np.ndarray, hw: tuple[int, int]) -> np.ndarray:
        h, w = hw
        img = np.asarray(rgb, dtype=np.float32)
        if img.shape[:2] != (h, w):
            interp = cv2.INTER_AREA if h < img.shape[0] else cv2.INTER_LINEAR
            img = cv2.resize(img, (w, h), interpolation=interp)
        if self.contract.normalization == "imagenet":
            img = (img - IMAGENET_MEAN) / IMAGENET_STD
        return np.ascontiguousarray(img.transpose(2, 0, 1)[None], dtype=np.float32)

    def predict(self, rgb: np.ndarray, hw: tuple[int, int] | None = None) -> np.ndarray:
        """Raw model output [H',W'] float32 for an RGB image [H,W,3] in [0,1], fed at `hw`."""
        hw = hw or self.input_hw(rgb.shape[:2])
        x = self.preprocess(rgb, hw)
        try:
            (out,) = self.session.run([self.output_name], {self.input_name: x})[:1]
        except Exception as exc:
            raise PanoError(self.path,
                            f"inference failed on a {list(x.shape)} input ({one_line(exc, 200)})") from None
        return self.check_output(np.asarray(out), hw)

    def check_output(self, out: np.ndarray, hw: tuple[int, int]) -> np.ndarray:
        shape = list(out.shape)
        arr = out
        while arr.ndim > 2 and arr.shape[0] == 1:
            arr = arr[0]
        h, w = hw
        ok = arr.ndim == 2 and min(arr.shape) >= 2
        if ok:
            # Same aspect as the input, to within a pixel of rounding (strided decoders).
            oh, ow = arr.shape
            ok = abs(oh * w / h - ow) <= max(1.0, w / h) + 1e-6
        if not ok:
            raise PanoError(
                self.path,
                f"model output has shape {shape} for a {[1, 3, h, w]} input; expected a depth map "
                f"[1,{h},{w}] or [1,1,{h},{w}] (or a scaled copy)",
            )
        return arr.astype(np.float32, copy=False)


def resize_map(values: np.ndarray, hw: tuple[int, int]) -> np.ndarray:
    """Bilinear resize of a float map; NaN pixels stay invalid (they spread to their neighbours)."""
    h, w = hw
    if values.shape == (h, w):
        return values.astype(np.float32, copy=False)
    return cv2.resize(values.astype(np.float32), (w, h), interpolation=cv2.INTER_LINEAR)


def run_equirect(model: OnnxDepthModel, rgb: np.ndarray, out_hw: tuple[int, int]) -> np.ndarray:
    """A 360° model on a panorama: raw output resized to `out_hw`."""
    return resize_map(model.predict(rgb), out_hw)
