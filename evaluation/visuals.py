"""Colour maps for error and depth images (fixed scales, so images compare across views and runs)."""

from __future__ import annotations

import numpy as np

def pyplot():
    """matplotlib.pyplot on the file-only Agg backend (reports and experiments draw into PNGs)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


#: Error maps map |render − gt| (mean over channels) 0 … ERROR_VMAX onto inferno.
ERROR_VMAX = 0.25


def colormap(values: np.ndarray, vmin: float, vmax: float, name: str) -> np.ndarray:
    """[H,W] values -> [H,W,3] float RGB in [0,1] through matplotlib colour map `name`."""
    import matplotlib

    t = (np.asarray(values, dtype=np.float64) - vmin) / max(vmax - vmin, 1e-12)
    t = np.clip(np.nan_to_num(t, nan=0.0), 0.0, 1.0)
    return matplotlib.colormaps[name](t)[..., :3].astype(np.float32)


def error_rgb(err: np.ndarray, vmax: float = ERROR_VMAX, valid: np.ndarray | None = None) -> np.ndarray:
    """|error| 0 … vmax on inferno; pixels the metrics leave out (`valid` False: masked) are grey."""
    rgb = colormap(err, 0.0, vmax, "inferno")
    if valid is not None:
        rgb[~np.asarray(valid, dtype=bool)] = NO_DATA_RGB
    return rgb


def depth_rgb(depth: np.ndarray, vmax: float | None = None) -> np.ndarray:
    """Depth in metres on turbo, 0 … vmax (default: the 99th percentile of positive depth);
    pixels with no depth (0) are black."""
    d = np.asarray(depth, dtype=np.float64)
    if vmax is None:
        vmax = depth_vmax(d)
    rgb = colormap(d, 0.0, vmax, "turbo")
    rgb[~(np.isfinite(d) & (d > 0))] = 0.0
    return rgb


#: Units of every false-colour map the report shows (the colour bar's label).
ERROR_UNITS = "mean |render − ground truth| over RGB (image intensity, 0…1)"
DEPTH_UNITS = "distance along the ray (m)"
DEPTH_ERROR_UNITS = "|rendered − ground-truth depth| (m)"
#: Colour of pixels a false-colour map has no value for (no ground truth): mid grey.
NO_DATA_RGB = (0.5, 0.5, 0.5)


def depth_vmax(depth: np.ndarray) -> float:
    """The top of depth_rgb's default scale: the 99th percentile of positive finite depth (1 when none)."""
    d = np.asarray(depth, dtype=np.float64)
    pos = d[np.isfinite(d) & (d > 0)]
    return float(np.percentile(pos, 99)) if pos.size else 1.0


def depth_error(pred: np.ndarray, gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """|pred − gt| in metres and the valid mask (ground truth finite and > 0, prediction finite),
    the pixels evaluation.metrics.depth_metrics counts."""
    d = np.asarray(pred, dtype=np.float64)
    g = np.asarray(gt, dtype=np.float64)
    if d.shape != g.shape:
        raise ValueError(f"depth shapes differ: {d.shape} vs {g.shape}")
    valid = np.isfinite(g) & (g > 0) & np.isfinite(d)
    err = np.where(valid, np.abs(np.where(valid, d, 0.0) - np.where(valid, g, 0.0)), np.nan)
    return err, valid


def depth_error_vmax(err: np.ndarray) -> float:
    """Top of a depth-error map's scale: the 99th percentile of the valid error (at least 1 mm)."""
    e = np.asarray(err, dtype=np.float64)
    e = e[np.isfinite(e)]
    return max(float(np.percentile(e, 99)), 1e-3) if e.size else 1.0


def depth_error_rgb(err: np.ndarray, vmax: float) -> np.ndarray:
    """|depth error| (m) 0 … vmax on inferno; pixels without ground truth (NaN) are grey."""
    e = np.asarray(err, dtype=np.float64)
    rgb = colormap(e, 0.0, vmax, "inferno")
    rgb[~np.isfinite(e)] = NO_DATA_RGB
    return rgb


def write_colorbar(path, vmin: float, vmax: float, cmap: str, label: str, width_in: float = 4.0) -> None:
    """A horizontal colour bar PNG: the colour map from vmin to vmax with ticks and `label` (units)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colorbar import ColorbarBase
    from matplotlib.colors import Normalize

    fig = plt.figure(figsize=(width_in, 0.85))
    ax = fig.add_axes([0.04, 0.55, 0.92, 0.3])
    cb = ColorbarBase(ax, cmap=matplotlib.colormaps[cmap], norm=Normalize(vmin=vmin, vmax=vmax),
                      orientation="horizontal")
    cb.set_label(label, fontsize=8)
    cb.ax.tick_params(labelsize=8)
    fig.savefig(path, dpi=100)
    plt.close(fig)
