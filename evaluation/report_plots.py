"""The report's figures: training curves, the step's extra series, stage durations, the floor plan."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from evaluation.visuals import pyplot

__all__ = ["plot_training_curves", "plot_training_extra", "plot_durations", "plot_floor_plan"]


def plot_training_curves(series: dict[str, np.ndarray], path: Path, final_test: tuple[float, float, str] | None = None
                         ) -> list[str]:
    """The main training chart, large: loss (top) and PSNR (bottom) against iteration.

    PSNR shows the training PSNR (raw faint, running mean solid when logged) and `final_test` =
    (iteration, PSNR, label) — the evaluate stage's mean — as a star. Returns the legend labels
    drawn (empty: nothing to draw, no file written)."""
    if "loss" not in series and "psnr" not in series:
        return []
    plt = pyplot()
    fig, (ax_l, ax_p) = plt.subplots(2, 1, figsize=(11, 8), sharex=True)
    labels: list[str] = []
    x = series["iteration"]

    def line(ax, key, colour, name):
        y = series.get(key)
        if y is None:
            return
        ok = np.isfinite(x) & np.isfinite(y)
        if not ok.any():
            return
        ema = series.get(f"ema_{key}")
        if ema is not None and np.isfinite(ema).any():
            # raw values jump from view to view: show them faint, their running mean solid
            ax.plot(x[ok], y[ok], lw=0.8, color=colour, alpha=0.3, label=f"{name} (per iteration)")
            oke = np.isfinite(x) & np.isfinite(ema)
            ax.plot(x[oke], ema[oke], lw=1.8, color=colour, label=f"{name} (running mean)")
            labels.extend([f"{name} (per iteration)", f"{name} (running mean)"])
        else:
            ax.plot(x[ok], y[ok], lw=1.6, color=colour, label=name)
            labels.append(name)
        if key == "loss" and np.all(y[ok] > 0):
            ax.set_yscale("log")

    line(ax_l, "loss", "C0", "training loss")
    line(ax_p, "psnr", "C1", "training PSNR")
    if final_test is not None and math.isfinite(final_test[1]):
        ax_p.plot([final_test[0]], [final_test[1]], "*", color="C3", ms=16, markeredgecolor="k",
                  label=final_test[2])
        ax_p.axhline(final_test[1], color="C3", ls="--", lw=0.8, alpha=0.6)
        labels.append(final_test[2])
    if not labels:
        plt.close(fig)
        return []
    ax_l.set_ylabel("loss (0.8·L1 + 0.2·D-SSIM + λ·layout)", fontsize=11)
    ax_l.set_title("training loss", fontsize=13)
    ax_p.set_ylabel("PSNR (dB)", fontsize=11)
    ax_p.set_title("PSNR", fontsize=13)
    ax_p.set_xlabel("iteration", fontsize=11)
    for ax in (ax_l, ax_p):
        ax.grid(alpha=0.3)
        ax.tick_params(labelsize=10)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=10, loc="best")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return labels


def plot_training_extra(series: dict[str, np.ndarray], path: Path) -> bool:
    """The smaller chart: #Gaussians against iteration, loss and PSNR against wall time."""
    panels = []
    if "num_gaussians" in series:
        panels.append(("iteration", "num_gaussians", "iteration", "# Gaussians", "C2"))
    if "elapsed" in series:
        panels += [("elapsed", k, "wall time (s)", t, c) for k, t, c in
                   (("loss", "training loss", "C0"), ("psnr", "training PSNR (dB)", "C1")) if k in series]
    if not panels:
        return False
    plt = pyplot()
    fig, axes = plt.subplots(1, len(panels), figsize=(4.5 * len(panels), 3.4), squeeze=False)
    for ax, (xk, yk, xlabel, title, colour) in zip(axes[0], panels):
        x, y = series[xk], series[yk]
        ok = np.isfinite(x) & np.isfinite(y)
        ax.plot(x[ok], y[ok], lw=1.2, color=colour)
        if yk == "loss" and ok.any() and np.all(y[ok] > 0):
            ax.set_yscale("log")
        ax.set_xlabel(xlabel)
        ax.set_title(title)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return True


def plot_durations(rows: list[dict], path: Path) -> bool:
    rows = [r for r in rows if r["duration_s"] is not None]
    if not rows:
        return False
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6, 0.45 * len(rows) + 1.0))
    names = [r["stage"] for r in rows][::-1]
    vals = [r["duration_s"] for r in rows][::-1]
    ax.barh(names, vals, color="C0")
    for y, v in enumerate(vals):
        ax.text(v, y, f" {v:.1f} s", va="center", fontsize=8)
    ax.set_xlabel("seconds (last run)")
    ax.set_xlim(0, max(vals) * 1.25 + 1e-6)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return True


def _ground_truth_rooms(scene) -> list[np.ndarray]:
    fp = scene.manifest.floor_plan if scene is not None else None
    if not fp:
        return []
    try:
        doc = json.loads(scene.path(fp).read_text())
        return [np.asarray(room["polygon"], dtype=float) for room in doc.get("rooms", [])]
    except (OSError, ValueError, KeyError, TypeError):
        return []


def plot_floor_plan(scene, path: Path, rooms: list[dict] | None = None) -> list[str]:
    """Every camera of the scene (train ● blue, test ▲ red, an arrow where the panorama's centre looks,
    each labelled with its view name) over the merged floor plan (`rooms`, the union artifact's) and
    the scene's ground-truth rooms where it has them, with a legend.

    Returns the camera labels written on the figure, in the scene's order (empty: nothing drawn)."""
    if scene is None or not scene.views:
        return []
    plt = pyplot()
    from matplotlib.lines import Line2D

    fig, ax = plt.subplots(figsize=(8, 8))
    handles = []
    for i, room in enumerate(rooms or []):
        try:
            rings = [np.asarray(room["polygon"], dtype=float)] + [np.asarray(h, dtype=float)
                                                                   for h in room.get("holes", [])]
        except (KeyError, TypeError, ValueError):
            continue
        for j, ring in enumerate(rings):
            if ring.ndim != 2 or len(ring) < 3:
                continue
            ax.fill(ring[:, 0], ring[:, 1], facecolor="none" if j else "C2", alpha=0.2 if not j else 1.0)
            closed = np.vstack([ring, ring[:1]])
            ax.plot(closed[:, 0], closed[:, 1], "-", color="C2", lw=2)
        if i == 0:
            handles.append(Line2D([], [], color="C2", lw=2, label="merged floor plan (union stage)"))
    gt_rooms = _ground_truth_rooms(scene)
    for poly in gt_rooms:
        closed = np.vstack([poly, poly[:1]])
        ax.plot(closed[:, 0], closed[:, 1], "k--", lw=1.2)
    if gt_rooms:
        handles.append(Line2D([], [], color="k", ls="--", lw=1.2, label="ground-truth rooms"))
    style = {"train": ("o", "C0", "train view"), "test": ("^", "C3", "test view")}
    labels: list[str] = []
    seen = set()
    xz = np.array([[v.position[0], v.position[2]] for v in scene.views])
    span = float(np.ptp(xz, axis=0).max()) if len(xz) > 1 else 1.0
    arrow = max(0.08 * max(span, 1.0), 0.2)
    for v in scene.views:
        marker, colour, name = style.get(v.split, ("s", "C7", str(v.split)))
        p = v.position
        fwd = v.pose_matrix[:3, 2]  # camera z axis in the world: where the panorama's centre looks
        ax.plot(p[0], p[2], marker, color=colour, ms=9, markeredgecolor="k")
        ax.arrow(p[0], p[2], arrow * fwd[0], arrow * fwd[2], head_width=0.3 * arrow, color=colour,
                 length_includes_head=True, zorder=4)
        ax.annotate(v.name, (p[0], p[2]), textcoords="offset points", xytext=(6, 6), fontsize=9,
                    color=colour, bbox={"boxstyle": "round,pad=0.15", "fc": "white", "ec": "none", "alpha": 0.6})
        labels.append(v.name)
        if v.split not in seen:
            seen.add(v.split)
            handles.append(Line2D([], [], marker=marker, color=colour, ls="none", ms=9, markeredgecolor="k",
                                  label=f"{name} ({sum(1 for w in scene.views if w.split == v.split)})"))
    ax.set_aspect("equal")
    ax.set_xlabel("world x (m)")
    ax.set_ylabel("world z (m)")
    ax.set_title("floor plan and cameras (seen from above; arrows: panorama centre direction)")
    ax.grid(alpha=0.3)
    ax.legend(handles=handles, loc="best", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return labels
