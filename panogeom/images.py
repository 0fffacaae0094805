"""Image I/O (OpenCV) in the project's convention: float32 RGB in [0, 1], [H, W, 3]."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from runfs.fsutil import native_write


def read_rgb(path: str | Path, size: tuple[int, int] | None = None) -> np.ndarray:
    """Read an image as float32 RGB [H,W,3] in [0,1]; optionally resize to (H, W) with area filtering."""
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise ValueError(f"{path}: unreadable image")
    img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    if size is not None and img.shape[:2] != tuple(size):
        h, w = size
        interp = cv2.INTER_AREA if h < img.shape[0] else cv2.INTER_LINEAR
        img = cv2.resize(img, (w, h), interpolation=interp)
    return img.astype(np.float32) / 255.0


def write_rgb(path: str | Path, rgb: np.ndarray) -> None:
    """Write float RGB in [0,1] (or uint8 RGB) as an 8-bit image."""
    arr = np.asarray(rgb)
    if arr.dtype != np.uint8:
        arr = (np.clip(arr, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    bgr = cv2.cvtColor(arr, cv2.COLOR_RGB2BGR)
    native_write(Path(path), lambda: cv2.imwrite(str(path), bgr), "image")
