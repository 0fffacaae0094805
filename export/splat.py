"""antimatter15's .splat: a headerless array of 32-byte records, one per Gaussian.

    offset  type        field
    0       3×float32   position x, y, z
    12      3×float32   scale (linear standard deviations, exp of the PLY's log scales)
    24      4×uint8     r, g, b, a: colour 0.5 + C0·f_dc and alpha sigmoid(opacity), ×255
    28      4×uint8     quaternion w, x, y, z (normalised), q·128 + 128

Little-endian, records sorted by decreasing exp(Σ log scale)·sigmoid(opacity) (the
"importance" order of antimatter15/splat's convert.py, which the viewer's progressive
loader relies on). Only the degree-0 colour survives: the format has no SH bands.
Unlike convert.py (which truncates), bytes are rounded to the nearest level.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gaussians.model import SH_C0, Gaussians

__all__ = ["SPLAT_DTYPE", "splat_bytes", "write_splat", "read_splat", "splat_order"]

SPLAT_DTYPE = np.dtype([("position", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rot", "u1", 4)])
assert SPLAT_DTYPE.itemsize == 32


def _np(t) -> np.ndarray:
    return t.detach().to("cpu").double().numpy()


def splat_order(g: Gaussians) -> np.ndarray:
    """Indices sorted by decreasing importance (scale product × opacity), ties by index."""
    log_vol = _np(g.log_scales).sum(1)
    importance = np.exp(log_vol) / (1.0 + np.exp(-_np(g.opacity_logits)))
    return np.argsort(-importance, kind="stable")


def _u8(x: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(x), 0, 255).astype(np.uint8)


def splat_bytes(g: Gaussians) -> bytes:
    """The .splat file content for `g`."""
    n = len(g)
    order = splat_order(g)
    rec = np.zeros(n, dtype=SPLAT_DTYPE)
    rec["position"] = _np(g.means)[order]
    rec["scale"] = np.exp(_np(g.log_scales))[order]
    rgb = 0.5 + SH_C0 * _np(g.sh_dc).reshape(n, 3)
    alpha = 1.0 / (1.0 + np.exp(-_np(g.opacity_logits)))
    rec["rgba"] = _u8(np.concatenate([rgb, alpha[:, None]], 1)[order] * 255.0)
    q = _np(g.quats)
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    q = np.where(norm > 0, q / np.maximum(norm, 1e-30), np.array([1.0, 0, 0, 0]))
    rec["rot"] = _u8(q[order] * 128.0 + 128.0)
    return rec.tobytes()


def write_splat(path: str | Path, g: Gaussians) -> Path:
    path = Path(path)
    path.write_bytes(splat_bytes(g))
    return path


def read_splat(path: str | Path) -> dict[str, np.ndarray]:
    """Decode a .splat as a viewer does: means, scales, rgb, alpha in [0,1], unit-ish
    (w, x, y, z) quaternions. Raises ValueError when the size is not a multiple of 32."""
    raw = Path(path).read_bytes()
    if len(raw) % SPLAT_DTYPE.itemsize:
        raise ValueError(f"{path}: {len(raw)} bytes is not a whole number of 32-byte .splat records")
    rec = np.frombuffer(raw, dtype=SPLAT_DTYPE)
    rgba = rec["rgba"].astype(np.float64) / 255.0
    quats = (rec["rot"].astype(np.float64) - 128.0) / 128.0
    return {
        "means": rec["position"].astype(np.float64),
        "scales": rec["scale"].astype(np.float64),
        "rgb": rgba[:, :3],
        "alpha": rgba[:, 3],
        "quats": quats,
    }
