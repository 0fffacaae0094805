"""`pano-pipe report`: one self-contained HTML page (every image base64-embedded) and a
Markdown twin with its PNGs beside it, built from a run folder's artifacts.

Sections: what limits the run (no priors, overfitting: evaluation/diagnosis.py) and every stage's
warnings beside the stage, when there are any; files (relative links to the model, fly-through
videos, config.yaml, logs);
test metrics (one row per view, the mean, best/worst view, LPIPS availability, render
speed); per evaluated view ground truth / render / error / depth and, with ground-truth
depth, that depth and the depth error — every false-colour map with a colour bar (units,
range); training (a large loss / PSNR chart against iteration with the final test PSNR,
and #Gaussians / wall time); the floor plan with every camera labelled; each stage's
parameters (table + config.yaml); stage durations. A missing artifact leaves its section
saying what to run, rather than failing the report. See docs/evaluation.md.
"""

from __future__ import annotations

import base64
import html
import json
import math
import os
import shutil
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from evaluation.report_text import fmt, html_text, md_text, missing_fields, url
from evaluation.visuals import pyplot
from evaluation.report_sections import (STAGE_SECTIONS, SectionContext, diagnosis_section, export_links,
                                        read_artifact, settings_section, settings_without_effect,
                                        warnings_section)
from runfs.errors import PanoError
from runfs.limits import load_npy
from runfs.paths import run_path


def stage_order() -> tuple[str, ...]:
    """The pipeline's stages in DAG order (pipeline/registry.py), as `run` executes them."""
    from pipeline.engine import topological_order
    from pipeline.registry import build_registry

    return tuple(topological_order(build_registry()))


METRIC_LABELS = {
    "psnr": "PSNR (dB) ↑",
    "ssim": "SSIM ↑",
    "ws_psnr": "WS-PSNR (dB) ↑",
    "lpips": "LPIPS ↓",
    "depth_abs_rel": "depth AbsRel ↓",
    "depth_rmse": "depth RMSE (m) ↓",
    "psnr_colorfit": "PSNR colour-fit (dB) ↑",
    "ssim_colorfit": "SSIM colour-fit ↑",
}

#: The train log's columns the report draws: its name -> the key gaussians/trainer.py writes.
LOG_KEYS = {"iteration": "iteration", "loss": "loss", "psnr": "psnr", "num_gaussians": "num_gaussians",
            "ema_loss": "ema_loss", "ema_psnr": "ema_psnr", "elapsed": "seconds"}


@dataclass
class ReportPaths:
    html: Path
    markdown: Path
    folder: Path
    sections: list[str] = field(default_factory=list)
    #: the camera names written on the floor-plan figure (empty when it was not drawn from the scene)
    camera_labels: list[str] = field(default_factory=list)
    #: relative href of every link the report holds (to files of the run and of the report folder)
    links: list[str] = field(default_factory=list)


# ----------------------------------------------------------------------------- reading the run


def read_jsonl(path: Path) -> list[dict]:
    out = []
    try:
        lines = path.read_text().splitlines()
    except OSError:
        return out
    for line in lines:
        line = line.strip()
        if not line:
            continue
        try:
            rec = json.loads(line)
        except ValueError:
            continue  # a half-written last line of an interrupted run
        if isinstance(rec, dict):
            out.append(rec)
    return out


def training_series(records: list[dict]) -> dict[str, np.ndarray]:
    """Columns of the train log under canonical names; a column is NaN where a record lacks it."""
    out: dict[str, np.ndarray] = {}
    for canon, key in LOG_KEYS.items():
        col = []
        found = False
        for r in records:
            v = r.get(key) if isinstance(r.get(key), int | float) else None  # null: a non-finite value
            found |= v is not None
            col.append(float(v) if v is not None else math.nan)
        if found:
            out[canon] = np.asarray(col)
    if "iteration" not in out and records:
        out["iteration"] = np.arange(1, len(records) + 1, dtype=float)
    return out


def stage_durations(run_dir: Path) -> list[dict]:
    """Per stage: last duration from its artifact, the number of runs and total seconds in run_log.jsonl."""
    log = read_jsonl(run_dir / "run_log.jsonl")
    rows = []
    order = stage_order()
    stages = list(order) + sorted(
        {r.get("stage") for r in log if isinstance(r.get("stage"), str) and r.get("stage") not in order}
    )
    for s in stages:
        art = read_artifact(run_dir, s)
        ok = [r for r in log if r.get("stage") == s and r.get("event") == "ok"]
        skipped = [r for r in log if r.get("stage") == s and r.get("event") == "skipped"]
        if art is None and not ok and not skipped:
            continue
        meta = (art or {}).get("meta", {})
        rows.append(
            {
                "stage": s,
                "duration_s": meta.get("duration_s"),
                "runs": len(ok),
                "total_s": sum(float(r.get("duration_s", 0.0)) for r in ok),
                "status": "done" if art else ("skipped: " + str(skipped[-1].get("reason", "")) if skipped else "—"),
                "warnings": len(meta.get("warnings", [])),
            }
        )
    return rows


# ----------------------------------------------------------------------------- figures


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


def stage_params(run_dir: Path) -> dict[str, dict]:
    """{stage: meta.params} of every stage with an artifact, in pipeline order."""
    order = stage_order()
    names = list(order) + sorted(
        p.parent.name for p in run_dir.glob("*/artifact.json") if p.parent.name not in order
    )
    out = {}
    for s in names:
        art = read_artifact(run_dir, s)
        if art is not None:
            params = art.get("meta", {}).get("params")
            out[s] = params if isinstance(params, dict) else {}
    return out


def write_config_yaml(path: Path, params: dict[str, dict], scene_name: str) -> None:
    import yaml

    doc = {"scene": scene_name, "stages": params}
    path.write_text("# the parameters each stage of this run ran with (artifact meta.params), written by "
                    "pano-pipe report\n" + yaml.safe_dump(doc, sort_keys=False, allow_unicode=True), encoding="utf-8")


def run_links(run_dir: Path, out_dir: Path, config_path: Path) -> list[tuple[str, str]]:
    """(relative href, text) for the files a reader wants from the run: the trained model, the
    fly-through videos, the configuration, the run and training logs, the metrics CSV. Only files
    that exist; hrefs are relative to the report folder so the two move together."""
    items: list[tuple[Path, str]] = []
    tr = read_artifact(run_dir, "train")
    train_data = (tr or {}).get("data") if isinstance((tr or {}).get("data"), dict) else {}
    ply = run_path(run_dir / "train", train_data.get("ply") or "point_cloud.ply", named_by="train/artifact.json")
    items.append((ply, "trained model (3D Gaussians, PLY)"))
    for video in sorted((run_dir / "render").glob("*.mp4")):
        if video.name.startswith("."):
            continue  # a render still being written (hidden temporary file)
        items.append((video, f"fly-through video {video.name}"))
    items += export_links(run_dir)
    items.append((config_path, "configuration: every stage's parameters (YAML)"))
    items.append((run_dir / "run_log.jsonl", "run log (run_log.jsonl)"))
    log = run_path(run_dir / "train", train_data.get("log") or "train_log.jsonl", named_by="train/artifact.json")
    items.append((log, "training log (train_log.jsonl)"))
    items.append((run_dir / "evaluate" / "metrics.csv", "per-view metrics (CSV)"))
    out = []
    for target, text in items:
        if target.is_file():
            href = Path(os.path.relpath(target.resolve(), out_dir.resolve())).as_posix()
            out.append((href, text))
    return out


def per_view_table(doc: _Doc, d: dict) -> None:
    """Each evaluated view's metrics (one row per view), then the mean; with two or more views a line
    naming the best and the worst view by PSNR, so a spread between views is not hidden by the mean."""
    views = d["views"]
    keys = [k for k in METRIC_LABELS if any(v.get(k) is not None for v in views)]
    extra = [("depth_valid_pixels", "depth px"), ("render_seconds", "render (s)")]
    extra = [(k, lbl) for k, lbl in extra if any(v.get(k) is not None for v in views)]
    rows = [[v["view"], str(v.get("split", d.get("split", ""))), *[fmt(v.get(k)) for k in keys],
             *[fmt(v.get(k)) for k, _ in extra]] for v in views]
    rows.append(["mean", "", *[fmt(d["mean"].get(k)) for k in keys], *["" for _ in extra]])
    doc.table(["view", "split", *[METRIC_LABELS[k] for k in keys], *[lbl for _, lbl in extra]], rows)
    scored = [v for v in views if isinstance(v.get("psnr"), (int, float)) and math.isfinite(v["psnr"])]
    if len(scored) >= 2:
        best = max(scored, key=lambda v: v["psnr"])
        worst = min(scored, key=lambda v: v["psnr"])
        doc.p(f"Per view: best {best['view']} {best['psnr']:.2f} dB, worst {worst['view']} "
              f"{worst['psnr']:.2f} dB ({best['psnr'] - worst['psnr']:.2f} dB apart).")
    masked = [f"{v['view']}: {v['mask']}" for v in views if v.get("mask")]
    if masked:  # which pixels the metrics leave out (docs/conventions.md, Masks)
        doc.p("Metrics over valid pixels only; masks applied: " + "; ".join(masked) + ".")


def view_images(edir: Path, v: dict, scene, view, img_dir: Path) -> tuple[list[tuple], list[str]]:
    """One evaluated view's images for the report: ground truth, render, error map and rendered depth
    (the evaluate stage's PNGs), and where the scene has ground-truth depth, that depth on the rendered
    depth's scale and the depth-error map (drawn here into img/). False-colour maps come with a colour
    bar (units, range) drawn into img/. Returns (items for _Doc.images, notes)."""
    from evaluation.visuals import (
        DEPTH_ERROR_UNITS,
        DEPTH_UNITS,
        ERROR_UNITS,
        ERROR_VMAX,
        depth_error,
        depth_error_rgb,
        depth_error_vmax,
        depth_rgb,
        depth_vmax,
        write_colorbar,
    )
    from panogeom.images import write_rgb

    prefix = f"view-{v['view']}"
    notes: list[str] = []

    def cbar(kind: str, vmin: float, vmax: float, cmap: str, units: str):
        path = img_dir / f"{prefix}-colorbar-{kind}.png"
        write_colorbar(path, vmin, vmax, cmap, units)
        return path, f"{units}, {vmin:.3g} … {vmax:.3g}"

    def named(key: str) -> Path:  # a file the artifact names: inside evaluate/, never through a link
        return run_path(edir, v[key], named_by="evaluate/artifact.json")

    items: list[tuple] = [(named("gt"), "ground truth"), (named("render"), "render")]
    items.append((named("error"), f"|error|, 0 … {ERROR_VMAX:g} (image intensity)",
                  cbar("error", 0.0, ERROR_VMAX, "inferno", ERROR_UNITS)))
    depth = None
    npy = named("depth_npy") if v.get("depth_npy") else None
    if npy is not None and npy.is_file():
        try:
            depth = load_npy(npy, pixels=True).astype(np.float64)
        except PanoError as e:  # a bad file must not stop the report
            notes.append(f"Rendered depth {npy.name} unreadable: {e.problem}")
            depth = None
    if depth is not None:
        dmax = depth_vmax(depth)
        items.append((named("depth"), f"rendered depth, 0 … {dmax:.3g} m",
                      cbar("depth", 0.0, dmax, "turbo", DEPTH_UNITS)))
    else:
        items.append((named("depth"), "rendered depth (scale not recorded: no depth .npy)"))
    items = [it for it in items if it[0].is_file()]

    gt_path = scene.gt_depth_path(view) if scene is not None and view is not None else None
    if gt_path is None or not gt_path.is_file():
        return items, notes
    if depth is None:
        notes.append("Ground-truth depth exists but the rendered depth (.npy) is missing: no depth-error map.")
        return items, notes
    from stages.evaluate import load_gt_depth

    try:
        gt = load_gt_depth(gt_path, depth.shape).astype(np.float64)
    except (PanoError, OSError, ValueError) as e:  # a bad file must not stop the report
        notes.append(f"Ground-truth depth {gt_path.name} unreadable: {e}")
        return items, notes
    gt_png = img_dir / f"{prefix}-gt-depth.png"
    write_rgb(gt_png, depth_rgb(gt, vmax=dmax))
    items.append((gt_png, f"ground-truth depth, 0 … {dmax:.3g} m", cbar("gt-depth", 0.0, dmax, "turbo", DEPTH_UNITS)))
    err, valid = depth_error(depth, gt)
    from schemas.scene_loader import valid_mask

    kept = valid_mask(scene, view, *depth.shape)  # the metrics' mask: masked pixels are grey here too
    if kept is not None:
        valid &= kept
        err = np.where(kept, err, np.nan)
    emax = depth_error_vmax(err)
    err_png = img_dir / f"{prefix}-depth-error.png"
    write_rgb(err_png, depth_error_rgb(err, emax))
    items.append((err_png, f"|depth error|, 0 … {emax:.3g} m",
                  cbar("depth-error", 0.0, emax, "inferno", DEPTH_ERROR_UNITS)))
    if valid.any():
        notes.append(f"Depth error over {int(valid.sum())} pixels with ground truth: mean "
                     f"{float(np.nanmean(err)):.3g} m, median {float(np.nanmedian(err)):.3g} m.")
    return items, notes


def ablation_side_by_side(ablation_json: Path, doc: _Doc, img_dir: Path, max_views: int = 2) -> None:
    """Held-out render, error and depth of the ablation's baseline (+ layout init) and 360 (+ layout reg)
    models side by side (seed 0 of each), so floaters and blur are visible: for the test view where
    the two differ most in PSNR and the first test view. Both depths share one colour scale."""
    from evaluation.experiments import PROJECTION_PAIR
    from evaluation.visuals import DEPTH_UNITS, depth_rgb, depth_vmax, write_colorbar
    from panogeom.images import write_rgb

    try:
        variants = {v["key"]: v for v in json.loads(ablation_json.read_text()).get("variants", [])}
    except (OSError, ValueError):
        return
    pair = [variants.get(k) for k in PROJECTION_PAIR]
    if any(v is None or not v.get("runs") for v in pair):
        return
    evals = []
    for v in pair:
        ev = read_artifact(Path(v["runs"][0]["dir"]), "evaluate")
        if ev is None:
            return
        evals.append((v, Path(v["runs"][0]["dir"]) / "evaluate", {r["view"]: r for r in ev["data"]["views"]}))
    common = [name for name in evals[0][2] if name in evals[1][2]]
    if not common:
        return
    gap = sorted(common, key=lambda n: -abs((evals[1][2][n]["psnr"] or 0) - (evals[0][2][n]["psnr"] or 0)))
    views = list(dict.fromkeys([gap[0], common[0]]))[:max_views]
    doc.h(3, "Held-out views: baseline against 360", "ablate-views")
    doc.p(f"Seed 0 of {pair[0]['label']} ({pair[0]['settings'].get('projection')}) and of {pair[1]['label']} "
          "(360): render, |error| and rendered depth of the same held-out panorama; depth on one scale.")
    for name in views:
        depths = []
        for _, edir, rows in evals:
            npy = edir / rows[name]["depth_npy"] if rows[name].get("depth_npy") else None
            depths.append(np.load(npy) if npy is not None and npy.is_file() else None)
        vmax = max((depth_vmax(d) for d in depths if d is not None), default=None)
        cbar = None
        if vmax is not None:
            cbar = (img_dir / f"ablate-{name}-colorbar-depth.png", f"{DEPTH_UNITS}, 0 … {vmax:.3g}")
            write_colorbar(cbar[0], 0.0, vmax, "turbo", DEPTH_UNITS)
        first = evals[0][2][name]
        doc.p(f"{name}: ground truth")
        doc.images([(evals[0][1] / first["gt"], "ground truth")], f"ablate-{name}")
        for (v, edir, rows), depth in zip(evals, depths):
            r, tag = rows[name], v["key"]
            items = [(edir / r["render"], f"{v['label']}: render, PSNR {fmt(r.get('psnr'), '.2f')} dB"),
                     (edir / r["error"], f"{v['label']}: |error|")]
            if depth is not None:
                png = img_dir / f"ablate-{name}-{tag}-depth.png"
                write_rgb(png, depth_rgb(depth, vmax=vmax))
                items.append((png, f"{v['label']}: rendered depth", cbar))
            doc.images([it for it in items if Path(it[0]).is_file()], f"ablate-{name}-{tag}")


# ----------------------------------------------------------------------------- assembling


def _model_cost_line(tr: dict | None, ev: dict) -> str | None:
    """What the evaluated model cost, beside its metrics (variants compare on the same footing only
    with these): Gaussians, iterations (one training image each), training time, and how the test
    panoramas were made."""
    if tr is None:
        return None
    td = tr["data"]
    images = td.get("train_images")
    proj = {"360": "360° splatting", "crops": "perspective crops", "cubemap": "cubemap"}.get(td.get("projection"),
                                                                                              td.get("projection"))
    how = f"test panoramas stitched from {ev['stitched']}" if ev.get("stitched") else "test panoramas rendered directly"
    return (f"Model: {fmt(td.get('num_gaussians'), ',')} Gaussians after {fmt(td.get('iterations'), ',')} "
            f"iterations (one training image each{f', from {images} training images' if images else ''}) "
            f"in {fmt(td.get('train_seconds'), '.1f')} s of training{_kernel_build_note(td)}; {proj}, {how}.")


def _kernel_build_note(td: dict) -> str:
    """The C++ kernel's first build on this machine, timed apart from training ('' when none)."""
    seconds = td.get("kernel_build_seconds")
    return "" if seconds is None else f" (after {fmt(seconds, '.1f')} s compiling the C++ kernel, once per machine)"


class _Doc:
    """Builds the HTML and Markdown side by side so they always hold the same content; text goes
    into both escaped (evaluation/report_text.py: html_text, md_text, url)."""

    def __init__(self, img_dir: Path):
        self.html: list[str] = []
        self.md: list[str] = []
        self.img_dir = img_dir

    def h(self, level: int, text: str, anchor: str | None = None) -> None:
        a = f' id="{anchor}"' if anchor else ""
        self.html.append(f"<h{level}{a}>{html_text(text)}</h{level}>")
        self.md.append(f"\n{'#' * level} {md_text(text)}\n")

    def p(self, text: str, cls: str = "") -> None:
        c = f' class="{cls}"' if cls else ""
        self.html.append(f"<p{c}>{html_text(text)}</p>")
        self.md.append(f"{'> ' if cls == 'warn' else ''}{md_text(text, paragraph_start=True)}\n")

    def table(self, header: list[str], rows: list[list[str]]) -> None:
        th = "".join(f"<th>{html_text(h)}</th>" for h in header)
        trs = "".join("<tr>" + "".join(f"<td>{html_text(c)}</td>" for c in r) + "</tr>" for r in rows)
        self.html.append(f"<table><thead><tr>{th}</tr></thead><tbody>{trs}</tbody></table>")
        self.md.append("| " + " | ".join(md_text(h) for h in header) + " |")
        self.md.append("|" + "---|" * len(header))
        for r in rows:
            self.md.append("| " + " | ".join(md_text(c) for c in r) + " |")
        self.md.append("")

    def details(self, summary: str, header: list[str], rows: list[list[str]]) -> None:
        """A table folded away under a one-line summary (<details>; GitHub's Markdown renders it too)."""
        self.html.append(f"<details><summary>{html_text(summary)}</summary>")
        self.md.append(f"<details><summary>{html_text(summary)}</summary>\n")
        self.table(header, rows)
        self.html.append("</details>")
        self.md.append("</details>\n")

    def links(self, items: list[tuple[str, str]]) -> None:
        """A bullet list of (relative href, text) links to files of the run."""
        lis = "".join(f'<li><a href="{html.escape(url(href))}">{html_text(text)}</a></li>' for href, text in items)
        self.html.append(f"<ul>{lis}</ul>")
        for href, text in items:
            self.md.append(f"- [{md_text(text)}]({url(href)})")
        self.md.append("")

    def _embed(self, src: Path, name_prefix: str) -> tuple[str, str]:
        """Copy `src` into img/ (unless it is there already); its base64 and its name in img/."""
        # gt/, renders/, errors/ and depth/ hold files of the same name: keep the folder in it
        dst_name = src.name if src.name.startswith(name_prefix) else f"{name_prefix}-{src.parent.name}-{src.stem}.png"
        dst = self.img_dir / dst_name
        if src.resolve() != dst.resolve():
            shutil.copyfile(src, dst)
        return base64.b64encode(dst.read_bytes()).decode("ascii"), dst_name

    def images(self, items: list[tuple], name_prefix: str) -> None:
        """A row of images with captions: embedded in the HTML, copied beside the Markdown.

        An item is (path, caption) or (path, caption, (colour bar path, units label)): a false-colour
        map then shows its colour bar, with the units, right under it."""
        figs, mds = [], []
        for item in items:
            src, caption = item[0], item[1]
            cbar = item[2] if len(item) > 2 else None
            b64, dst_name = self._embed(src, name_prefix)
            extra, md_extra = "", ""
            if cbar is not None:
                cb64, cb_name = self._embed(cbar[0], name_prefix)
                alt = f"colour bar: {cbar[1]}"
                extra = f'<img class="cbar" alt="{html_text(alt)}" src="data:image/png;base64,{cb64}">'
                md_extra = f"<br>![{md_text(alt)}]({url(f'{self.img_dir.name}/{cb_name}')})"
            figs.append(
                f'<figure><img alt="{html_text(caption)}" src="data:image/png;base64,{b64}">{extra}'
                f"<figcaption>{html_text(caption)}</figcaption></figure>"
            )
            mds.append(f"![{md_text(caption)}]({url(f'{self.img_dir.name}/{dst_name}')}){md_extra}")
        cls = "row single" if len(figs) == 1 else "row"
        self.html.append(f'<div class="{cls}">' + "".join(figs) + "</div>")
        if any(len(i) > 2 and i[2] is not None for i in items):
            # maps with colour bars: one table cell each, so a bar stays under its map
            self.md.append("| " + " | ".join(md_text(i[1]) for i in items) + " |")
            self.md.append("|" + "---|" * len(items))
            self.md.append("| " + " | ".join(mds) + " |\n")
        else:
            self.md.append(" ".join(mds) + "\n")


_CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,sans-serif;margin:2em auto;max-width:1200px;color:#222;padding:0 1em}
h1{border-bottom:2px solid #444}h2{border-bottom:1px solid #ccc;margin-top:2em}
table{border-collapse:collapse;margin:1em 0}td,th{border:1px solid #ccc;padding:4px 10px;text-align:right}
th{background:#f0f0f0}td:first-child,th:first-child{text-align:left}
.row{display:flex;flex-wrap:wrap;gap:8px}figure{margin:0;flex:1 1 260px;max-width:100%}
figure img{width:100%;image-rendering:pixelated;border:1px solid #ddd}
figure img.cbar{image-rendering:auto;border:none}figcaption{font-size:.8em;color:#555}
.row:not(.single) figure{max-width:calc(25% - 6px)}
.single figure{flex:0 1 760px}
.warn{background:#fff4d6;border-left:4px solid #e0a800;padding:.5em}.note{color:#666}
details{margin:1em 0}details summary{cursor:pointer;color:#245}
"""


def build_report(run_dir: Path, scene=None, out_dir: Path | None = None,
                 states: dict[str, str] | None = None) -> ReportPaths:
    """Write report.html (self-contained) and report.md (+ img/, config.yaml) into `out_dir`
    (default <run>/report/), whole or not at all: built in a temporary sibling folder that then
    replaces the previous report (a full disk leaves the previous one as it was, not half a new one).

    `states` (stage -> up-to-date / stale / missing / skipped, from Engine.plan) adds a column
    saying whether each stage's result is current."""
    from dataclasses import replace

    from runfs.fsutil import atomic_folder

    run_dir = Path(run_dir)
    final = Path(out_dir) if out_dir is not None else run_path(run_dir, "report")
    with atomic_folder(final) as tmp:
        paths = _write_report(run_dir, scene, tmp, states)
    return replace(paths, html=final / paths.html.name, markdown=final / paths.markdown.name, folder=final)


def _write_report(run_dir: Path, scene, out_dir: Path, states: dict[str, str] | None) -> ReportPaths:
    img_dir = run_path(out_dir, "img")
    img_dir.mkdir(parents=True)
    doc = _Doc(img_dir)
    sections: list[str] = []
    name = scene.name if scene is not None else run_dir.name
    doc.h(1, f"pano-pipe report: {name}")
    doc.p(f"run folder {run_dir} · generated {datetime.now(timezone.utc):%Y-%m-%d %H:%M UTC}", "note")
    camera_labels: list[str] = []

    # -- what limits this run (no priors, overfitting), then every stage's warnings: first, where they are seen
    section_ctx = SectionContext(run_dir=run_dir, scene=scene, out_dir=out_dir, img_dir=img_dir)
    for section in (diagnosis_section, warnings_section):
        section_id = section(doc, section_ctx)
        if section_id:
            sections.append(section_id)

    # -- files: model, videos, configuration, logs (relative links: the report moves with the run)
    out_dir.mkdir(parents=True, exist_ok=True)
    params = stage_params(run_dir)
    config_path = out_dir / "config.yaml"
    config_path.unlink(missing_ok=True)  # never link a stale one
    if params:
        write_config_yaml(config_path, params, name)
    link_items = run_links(run_dir, out_dir, config_path)
    doc.h(2, "Files", "files")
    if link_items:
        sections.append("files")
        doc.links(link_items)
    else:
        doc.p("No files of the run yet (model, videos, configuration, run log).", "warn")
    links = [href for href, _ in link_items]

    not_applied = settings_without_effect(run_dir, scene)  # named where each setting is shown

    # -- metrics
    ev = read_artifact(run_dir, "evaluate")
    from evaluation.visuals import DEPTH_ERROR_UNITS, DEPTH_UNITS, ERROR_UNITS, ERROR_VMAX

    doc.h(2, "Test metrics", "metrics")
    if ev is None:
        doc.p("No evaluation yet: run `pano-pipe run all SCENE` (or `pano-pipe run evaluate SCENE`).", "warn")
    else:
        sections.append("metrics")
        d = ev["data"]
        if d.get("on_train_views"):
            doc.p("The scene has no test views: these numbers are measured on the TRAINING views.", "warn")
        per_view_table(doc, d)
        missing = missing_fields(d.get("mean") or {}, ("psnr", "ssim", "ws_psnr"))
        if missing:  # a model that diverged renders nothing measurable: say so, show the rest
            doc.p(f"Missing from the evaluation (null or NaN in evaluate/artifact.json): {', '.join(missing)}; "
                  "a model with NaN parameters renders nothing to measure: train it again.", "warn")
        if not d.get("lpips_available"):
            said = any(d.get("lpips_reason") and d["lpips_reason"] in w for w in ev["meta"].get("warnings") or [])
            doc.p("LPIPS unavailable: see the evaluate stage's warning (Stage warnings)." if said else
                  f"LPIPS unavailable: {d.get('lpips_reason')}", "warn")
        h, w = (list(d.get("resolution") or []) + ["?", "?"])[:2]
        doc.p(
            f"Render speed {fmt(d.get('fps'), '.2f')} FPS (median of {fmt(d.get('fps_repeats'))}) for a {h}×{w} (H×W) "
            f"panorama, backend {fmt(d.get('backend'))} on {fmt(d.get('device'))}, {fmt(d.get('threads'))} torch "
            f"threads, {fmt(d.get('num_gaussians'), ',')} Gaussians; evaluated at {h}×{w} on the "
            f"{fmt(d.get('split'))} split."
        )
        model_cost = _model_cost_line(read_artifact(run_dir, "train"), d)
        if model_cost:
            doc.p(model_cost)

        # -- per view
        doc.h(2, "Views: ground truth / render / error / depth", "views")
        sections.append("views")
        doc.p("Every false-colour map has its colour bar, with units and range, under it. Error maps: "
              f"{ERROR_UNITS}, inferno, fixed scale 0 … {ERROR_VMAX:g} so they compare across views and "
              "runs; grey = pixels the metrics leave out (the view's mask, the nadir cap). "
              f"Depth: {DEPTH_UNITS}, turbo, 0 … the rendered depth's 99th percentile (ground-truth depth on "
              "the same scale); black = nothing rendered / no depth. Depth error: "
              f"{DEPTH_ERROR_UNITS}, inferno, 0 … its 99th percentile; grey = no ground truth.", "note")
        scene_views = {sv.name: sv for sv in scene.views} if scene is not None else {}
        for v in d.get("views") or []:
            doc.h(3, f"{v['view']} — PSNR {fmt(v.get('psnr'), '.2f')} dB, SSIM {fmt(v.get('ssim'), '.3f')}")
            items, notes = view_images(run_dir / "evaluate", v, scene, scene_views.get(v["view"]), img_dir)
            doc.images(items, f"view-{v['view']}")
            for n in notes:
                doc.p(n, "note")

    # -- training curves
    tr = read_artifact(run_dir, "train")
    doc.h(2, "Training", "training")
    if tr is None:
        doc.p("No training artifact: run `pano-pipe run train SCENE`.", "warn")
    else:
        td = tr["data"]
        reg_note = not_applied.get(("train", "layout_reg"))
        summary = [
            ["iterations", fmt(td.get("iterations"))], ["Gaussians", fmt(td.get("num_gaussians"))],
            ["training seconds", fmt(td.get("train_seconds"))],
            *([["C++ kernel build seconds (once)", fmt(td["kernel_build_seconds"])]]
              if td.get("kernel_build_seconds") is not None else []),
            ["resolution (H×W)", "×".join(str(x) for x in td.get("resolution", []))],
            ["init", fmt(td.get("init"))], ["projection", fmt(td.get("projection"))],
            ["layout regularisation",
             fmt(td.get("layout_reg")) + (f" (not applied: {reg_note})" if reg_note else "")],
            ["λ layout", fmt(td.get("lambda_layout"))],
            ["preset", fmt(td.get("preset"))], ["backend", fmt(td.get("backend"))],
            ["final train PSNR", fmt(td.get("final_train_psnr"))],
        ]
        doc.table(["setting", "value"], summary)
        series = training_series(read_jsonl(run_path(run_dir / "train", td.get("log") or "train_log.jsonl",
                                                     named_by="train/artifact.json")))
        final_test = None
        if ev is not None and isinstance(ev["data"].get("mean", {}).get("psnr"), (int, float)):
            last_it = td.get("iterations")
            if not isinstance(last_it, (int, float)):
                its = series.get("iteration")
                last_it = float(np.nanmax(its)) if its is not None and np.isfinite(its).any() else 0.0
            n = len(ev["data"].get("views", []))
            label = (f"{ev['data'].get('split', 'test')} PSNR after training (evaluate, mean of {n} "
                     f"view{'s' if n != 1 else ''})")
            final_test = (float(last_it), float(ev["data"]["mean"]["psnr"]), label)
        curves = img_dir / "training_curves.png"
        labels = plot_training_curves(series, curves, final_test) if series else []
        if labels:
            sections.append("training")
            doc.images([(curves, "loss and PSNR against iteration")], "training")
            doc.p("Test PSNR is measured only at the end, by the evaluate stage (the star)." if final_test else
                  "There is no evaluation yet: the chart shows training PSNR only.", "note")
            extra = img_dir / "training_extra.png"
            if plot_training_extra(series, extra):
                doc.images([(extra, "# Gaussians against iteration; loss and PSNR against wall time")], "training")
        else:
            doc.p("The training log holds no loss / PSNR records.", "warn")

    # -- floor plan
    doc.h(2, "Floor plan and cameras", "floorplan")
    un = read_artifact(run_dir, "union")
    plan = img_dir / "floorplan.png"
    union_png = run_dir / "union" / un["data"].get("drawing", "floor_plan.png") if un is not None else None
    labels = plot_floor_plan(scene, plan, un["data"].get("rooms") if un is not None else None)
    camera_labels[:] = labels
    drawn = bool(labels)
    if drawn and un is not None:
        doc.p(f"Merged floor plan from the union stage ({fmt(un['data'].get('area_m2'))} m²), every camera "
              f"of the scene (train and test) from its poses.")
    elif drawn:
        doc.p("No union artifact (layout skipped or not run): cameras from the scene's poses, "
              "over the ground-truth rooms where the scene has them.", "note")
    elif union_png is not None and union_png.is_file():
        shutil.copyfile(union_png, plan)  # no scene given: the union stage's own drawing
        doc.p(f"Merged floor plan from the union stage ({fmt(un['data'].get('area_m2'))} m²) with the "
              "training cameras (no scene given: test cameras not drawn).")
        drawn = True
    if drawn:
        sections.append("floorplan")
        doc.images([(plan, "floor plan with cameras")], "floorplan")
        if labels:
            doc.p("Cameras: " + ", ".join(f"{v.name} ({v.split})" for v in scene.views) + ".", "note")
    else:
        doc.p("No floor plan: run the union stage.", "warn")

    # -- poses: how the cameras were placed (evaluation/report_poses.py), first as in the DAG
    from evaluation.report_poses import add_poses_section

    if add_poses_section(doc, run_dir):
        sections.append("poses")

    # -- what each stage did (layout, depth alignment, ...): present only when the stage ran
    for section in STAGE_SECTIONS:
        section_id = section(doc, section_ctx)
        if section_id:
            sections.append(section_id)

    # -- configuration: non-default values first, the full table folded; settings without effect named
    train_art = read_artifact(run_dir, "train")
    used = {"train": (train_art.get("data") or {}).get("settings") or {}} if train_art else {}
    if settings_section(doc, params, not_applied, used):
        sections.append("config")

    # -- durations
    doc.h(2, "Stage durations", "durations")
    rows = stage_durations(run_dir)
    if rows:
        sections.append("durations")
        header = ["stage", "last run (s)", "runs logged", "total logged (s)", "status", "warnings"]
        body = [[r["stage"], fmt(r["duration_s"]), str(r["runs"]), fmt(r["total_s"]), r["status"], str(r["warnings"])]
                for r in rows]
        if states:
            header.append("now")
            for b, r in zip(body, rows):
                b.append(states.get(r["stage"], "—"))
        doc.table(header, body)
        chart = img_dir / "durations.png"
        if plot_durations(rows, chart):
            doc.images([(chart, "stage durations (last run)")], "durations")
    else:
        doc.p("No stage has run in this folder.", "warn")

    # -- experiments, when `pano-pipe ablate` / `sweep` have written into this run folder
    for sub, stem, title in (("ablate", "ablation", "Ablation"), ("sweep", "sweep", "Accuracy vs cost sweep")):
        doc_json = run_dir / sub / f"{stem}.json"
        chart = run_dir / sub / f"{stem}.png"
        if not (doc_json.is_file() and chart.is_file()):
            continue
        doc.h(2, title, sub)
        sections.append(sub)
        md_file = run_dir / sub / f"{stem}.md"
        table = [ln for ln in md_file.read_text().splitlines() if ln.startswith("|")] if md_file.is_file() else []
        if len(table) > 2:
            cells = [[c.strip() for c in ln.strip("|").split("|")] for ln in table]
            doc.table(cells[0], cells[2:])
        try:
            for note in json.loads(doc_json.read_text()).get("notes", []):
                doc.p(note)
        except ValueError:
            pass
        doc.images([(chart, f"{stem} ({sub}/{stem}.md)")], sub)
        if sub == "ablate":
            ablation_side_by_side(doc_json, doc, img_dir)

    out_dir.mkdir(parents=True, exist_ok=True)
    page = (
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
        f"<title>pano-pipe report: {html_text(name)}</title><style>{_CSS}</style></head><body>\n"
        + "\n".join(doc.html)
        + "\n</body></html>\n"
    )
    html_path = out_dir / "report.html"
    md_path = out_dir / "report.md"
    html_path.write_text(page, encoding="utf-8")
    md_path.write_text("\n".join(doc.md).lstrip() + "\n", encoding="utf-8")
    return ReportPaths(html_path, md_path, out_dir, sections, camera_labels, links)
