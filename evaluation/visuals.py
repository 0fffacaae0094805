"""Colour maps for error and depth images (fixed scales, so images compare across views and runs)."""

from __future__ import annotations

import numpy as np

#: Error maps map |render − gt| (mean over channels) 0 … ERROR_VMAX onto inferno.
ERROR_VMAX = 0.25


def colormap(values: np.ndarray, vmin: float, vmax: float, name: str) -> np.ndarray:
    """[H,W] values -> [H,W,3] float RGB in [0,1] through matplotlib colour map `name`."""
    import matplotlib

    t = (np.asarray(values, dtype=np.float64) - vmin) / max(vmax - vmin, 1e-12)
    t = np.clip(np.nan_to_num(t, nan=0.0), 0.0, 1.0)
    return matplotlib.colormaps[name](t)[..., :3].astype(np.float32)


def error_rgb(err: np.ndarray, vmax: float = ERROR_VMAX) -> np.ndarray:
    return colormap(err, 0.0, vmax, "inferno")


def depth_rgb(depth: np.ndarray, vmax: float | None = None) -> np.ndarray:
    """Depth in metres on turbo, 0 … vmax (default: the 99th percentile of positive depth);
    pixels with no depth (0) are black."""
    d = np.asarray(depth, dtype=np.float64)
    pos = d[np.isfinite(d) & (d > 0)]
    if vmax is None:
        vmax = float(np.percentile(pos, 99)) if pos.size else 1.0
    rgb = colormap(d, 0.0, vmax, "turbo")
    rgb[~(np.isfinite(d) & (d > 0))] = 0.0
    return rgb
