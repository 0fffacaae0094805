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

import json
import math
import os
import shutil
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from evaluation.report_doc import CSS, ReportDoc
from evaluation.report_plots import plot_durations, plot_floor_plan, plot_training_curves, plot_training_extra
from evaluation.report_text import fmt, html_text, missing_fields
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
    "flat_psnr": "PSNR of a flat image (dB)",
    "flat_ssim": "SSIM of a flat image",
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


def per_view_table(doc: ReportDoc, d: dict) -> None:
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
    bar (units, range) drawn into img/. Returns (items for ReportDoc.images, notes)."""
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


def ablation_side_by_side(ablation_json: Path, doc: ReportDoc, img_dir: Path, max_views: int = 2) -> None:
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
            f"iterations (one training image each{f', from {images} training image' + 's' * (images != 1) if images else ''}) "
            f"in {fmt(td.get('train_seconds'), '.1f')} s of training{_kernel_build_note(td)}; {proj}, {how}.")


def _kernel_build_note(td: dict) -> str:
    """The C++ kernel's first build on this machine, timed apart from training ('' when none)."""
    seconds = td.get("kernel_build_seconds")
    return "" if seconds is None else f" (after {fmt(seconds, '.1f')} s compiling the C++ kernel, once per machine)"


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
    doc = ReportDoc(img_dir)
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
        f"<title>pano-pipe report: {html_text(name)}</title><style>{CSS}</style></head><body>\n"
        + "\n".join(doc.html)
        + "\n</body></html>\n"
    )
    html_path = out_dir / "report.html"
    md_path = out_dir / "report.md"
    html_path.write_text(page, encoding="utf-8")
    md_path.write_text("\n".join(doc.md).lstrip() + "\n", encoding="utf-8")
    return ReportPaths(html_path, md_path, out_dir, sections, camera_labels, links)
