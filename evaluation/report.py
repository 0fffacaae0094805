"""`pano-pipe report`: one self-contained HTML page (every image base64-embedded) and a
Markdown twin with its PNGs beside it, built from a run folder's artifacts.

Sections: test metrics (table, LPIPS availability, render speed); per evaluated
view ground truth / render / error / depth; training curves (loss, PSNR, #Gaussians
against iteration and against wall time); the floor plan with cameras (the union
stage's drawing, else one drawn from the scene's poses and ground-truth plan);
stage durations (artifacts' meta.duration_s and run_log.jsonl). A missing
artifact leaves its section saying what to run, rather than failing the report.
"""

from __future__ import annotations

import base64
import html
import json
import math
import shutil
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

STAGE_ORDER = ("layout", "depth", "union", "sampling", "align", "train", "evaluate")
METRIC_LABELS = {
    "psnr": "PSNR (dB) ↑",
    "ssim": "SSIM ↑",
    "ws_psnr": "WS-PSNR (dB) ↑",
    "lpips": "LPIPS ↓",
    "depth_abs_rel": "depth AbsRel ↓",
    "depth_rmse": "depth RMSE (m) ↓",
}

# Key names the train log may use (the first present wins), so the report stays
# readable if the train stage renames a field.
LOG_KEYS = {
    "iteration": ("iteration", "iter", "step", "it"),
    "loss": ("loss", "total_loss", "loss_total"),
    "psnr": ("psnr", "train_psnr", "psnr_train"),
    "num_gaussians": ("num_gaussians", "n_gaussians", "gaussians", "num"),
    "ema_loss": ("ema_loss",),
    "ema_psnr": ("ema_psnr",),
    "elapsed": ("elapsed_s", "elapsed", "wall_s", "time_s", "seconds", "elapsed_seconds", "time", "wall_time"),
}


@dataclass
class ReportPaths:
    html: Path
    markdown: Path
    folder: Path
    sections: list[str] = field(default_factory=list)


# ----------------------------------------------------------------------------- reading the run


def read_artifact(run_dir: Path, stage: str) -> dict | None:
    try:
        return json.loads((run_dir / stage / "artifact.json").read_text())
    except (OSError, ValueError):
        return None


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
    for canon, keys in LOG_KEYS.items():
        col = []
        found = False
        for r in records:
            v = next((r[k] for k in keys if k in r and isinstance(r[k], (int, float))), None)
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
    stages = list(STAGE_ORDER) + sorted(
        {r.get("stage") for r in log if r.get("stage") and r.get("stage") not in STAGE_ORDER}
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


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_training_curves(series: dict[str, np.ndarray], path: Path) -> bool:
    """Loss, PSNR and #Gaussians vs iteration (top row) and vs wall time (bottom row)."""
    metrics = [k for k in ("loss", "psnr", "num_gaussians") if k in series]
    if not metrics:
        return False
    plt = _plt()
    xs = [("iteration", "iteration")] + ([("elapsed", "wall time (s)")] if "elapsed" in series else [])
    fig, axes = plt.subplots(len(xs), len(metrics), figsize=(4.2 * len(metrics), 3.2 * len(xs)), squeeze=False)
    titles = {"loss": "training loss", "psnr": "training PSNR (dB)", "num_gaussians": "# Gaussians"}
    for i, (xk, xlabel) in enumerate(xs):
        for j, m in enumerate(metrics):
            ax = axes[i][j]
            x, y = series[xk], series[m]
            ok = np.isfinite(x) & np.isfinite(y)
            colour = ("C0", "C1", "C2")[j]
            ema = series.get(f"ema_{m}")
            if ema is not None and np.isfinite(ema).any():
                # raw values jump from view to view: show them faint, their running mean solid
                ax.plot(x[ok], y[ok], lw=0.8, color=colour, alpha=0.3, label="per iteration")
                oke = np.isfinite(x) & np.isfinite(ema)
                ax.plot(x[oke], ema[oke], lw=1.4, color=colour, label="running mean")
                ax.legend(fontsize=7)
            else:
                ax.plot(x[ok], y[ok], lw=1.2, color=colour)
            if m == "loss" and ok.any() and np.all(y[ok] > 0):
                ax.set_yscale("log")
            ax.set_xlabel(xlabel)
            ax.set_title(titles[m])
            ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return True


def plot_durations(rows: list[dict], path: Path) -> bool:
    rows = [r for r in rows if r["duration_s"] is not None]
    if not rows:
        return False
    plt = _plt()
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


def draw_floor_plan_fallback(scene, path: Path) -> bool:
    """Cameras from the scene's poses (train ●, test ▲) over the ground-truth rooms where the scene has them."""
    if scene is None:
        return False
    plt = _plt()
    fig, ax = plt.subplots(figsize=(5, 5))
    fp = scene.manifest.floor_plan
    if fp and scene.path(fp).is_file():
        try:
            doc = json.loads(scene.path(fp).read_text())
            for room in doc.get("rooms", []):
                poly = np.asarray(room["polygon"], dtype=float)
                poly = np.vstack([poly, poly[:1]])
                ax.plot(poly[:, 0], poly[:, 1], "k-", lw=1.5)
        except (OSError, ValueError, KeyError):
            pass
    for v in scene.views:
        p = v.position
        fwd = v.pose_matrix[:3, 2]  # camera z axis in the world: where the panorama's centre looks
        marker = "o" if v.split == "train" else "^"
        color = "C0" if v.split == "train" else "C3"
        ax.plot(p[0], p[2], marker, color=color)
        ax.arrow(p[0], p[2], 0.3 * fwd[0], 0.3 * fwd[2], head_width=0.06, color=color)
        ax.annotate(v.name, (p[0], p[2]), textcoords="offset points", xytext=(4, 4), fontsize=7)
    ax.set_aspect("equal")
    ax.set_xlabel("world x (m)")
    ax.set_ylabel("world z (m)")
    ax.set_title("cameras (● train, ▲ test)")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return True


# ----------------------------------------------------------------------------- assembling


def _fmt(v, digits: int = 4) -> str:
    if v is None:
        return "—"
    if isinstance(v, float):
        if math.isnan(v):
            return "—"
        return f"{v:.{digits}g}"
    return str(v)


class _Doc:
    """Builds the HTML and Markdown side by side so they always hold the same content."""

    def __init__(self, img_dir: Path):
        self.html: list[str] = []
        self.md: list[str] = []
        self.img_dir = img_dir

    def h(self, level: int, text: str, anchor: str | None = None) -> None:
        a = f' id="{anchor}"' if anchor else ""
        self.html.append(f"<h{level}{a}>{html.escape(text)}</h{level}>")
        self.md.append(f"\n{'#' * level} {text}\n")

    def p(self, text: str, cls: str = "") -> None:
        c = f' class="{cls}"' if cls else ""
        self.html.append(f"<p{c}>{html.escape(text)}</p>")
        self.md.append(f"{'> ' if cls == 'warn' else ''}{text}\n")

    def table(self, header: list[str], rows: list[list[str]]) -> None:
        th = "".join(f"<th>{html.escape(h)}</th>" for h in header)
        trs = "".join("<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in r) + "</tr>" for r in rows)
        self.html.append(f"<table><thead><tr>{th}</tr></thead><tbody>{trs}</tbody></table>")
        self.md.append("| " + " | ".join(header) + " |")
        self.md.append("|" + "---|" * len(header))
        for r in rows:
            self.md.append("| " + " | ".join(c.replace("|", "\\|") for c in r) + " |")
        self.md.append("")

    def images(self, items: list[tuple[Path, str]], name_prefix: str) -> None:
        """A row of images with captions: embedded in the HTML, copied beside the Markdown."""
        figs, mds = [], []
        for src, caption in items:
            # gt/, renders/, errors/ and depth/ hold files of the same name: keep the folder in it
            dst_name = (
                src.name if src.name.startswith(name_prefix) else f"{name_prefix}-{src.parent.name}-{src.stem}.png"
            )
            dst = self.img_dir / dst_name
            if src.resolve() != dst.resolve():
                shutil.copyfile(src, dst)
            b64 = base64.b64encode(dst.read_bytes()).decode("ascii")
            figs.append(
                f'<figure><img alt="{html.escape(caption)}" src="data:image/png;base64,{b64}">'
                f"<figcaption>{html.escape(caption)}</figcaption></figure>"
            )
            mds.append(f"![{caption}]({self.img_dir.name}/{dst_name})")
        cls = "row single" if len(figs) == 1 else "row"
        self.html.append(f'<div class="{cls}">' + "".join(figs) + "</div>")
        self.md.append(" ".join(mds) + "\n")


_CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,sans-serif;margin:2em auto;max-width:1200px;color:#222;padding:0 1em}
h1{border-bottom:2px solid #444}h2{border-bottom:1px solid #ccc;margin-top:2em}
table{border-collapse:collapse;margin:1em 0}td,th{border:1px solid #ccc;padding:4px 10px;text-align:right}
th{background:#f0f0f0}td:first-child,th:first-child{text-align:left}
.row{display:flex;flex-wrap:wrap;gap:8px}figure{margin:0;flex:1 1 260px;max-width:100%}
figure img{width:100%;image-rendering:pixelated;border:1px solid #ddd}figcaption{font-size:.8em;color:#555}
.single figure{flex:0 1 760px}
.warn{background:#fff4d6;border-left:4px solid #e0a800;padding:.5em}.note{color:#666}
"""


def build_report(run_dir: Path, scene=None, out_dir: Path | None = None, states: dict[str, str] | None = None) -> ReportPaths:
    """Write report.html (self-contained) and report.md (+ img/) into `out_dir` (default <run>/report/).

    `states` (stage -> up-to-date / stale / missing / skipped, from Engine.plan) adds a column
    saying whether each stage's result is current."""
    run_dir = Path(run_dir)
    out_dir = Path(out_dir) if out_dir is not None else run_dir / "report"
    img_dir = out_dir / "img"
    if img_dir.exists():
        shutil.rmtree(img_dir)
    img_dir.mkdir(parents=True)
    doc = _Doc(img_dir)
    sections: list[str] = []
    name = scene.name if scene is not None else run_dir.name
    doc.h(1, f"pano-pipe report: {name}")
    doc.p(f"run folder {run_dir} · generated {datetime.now(timezone.utc):%Y-%m-%d %H:%M UTC}", "note")

    # -- metrics
    ev = read_artifact(run_dir, "evaluate")
    doc.h(2, "Test metrics", "metrics")
    if ev is None:
        doc.p("No evaluation yet: run `pano-pipe run all SCENE` (or `pano-pipe run evaluate SCENE`).", "warn")
    else:
        sections.append("metrics")
        d = ev["data"]
        if d.get("on_train_views"):
            doc.p("The scene has no test views: these numbers are measured on the TRAINING views.", "warn")
        keys = [k for k in METRIC_LABELS if any(v.get(k) is not None for v in d["views"])]
        rows = [[v["view"], *[_fmt(v.get(k)) for k in keys]] for v in d["views"]]
        rows.append(["mean", *[_fmt(d["mean"].get(k)) for k in keys]])
        doc.table(["view", *[METRIC_LABELS[k] for k in keys]], rows)
        if not d.get("lpips_available"):
            doc.p(f"LPIPS unavailable: {d.get('lpips_reason')}", "warn")
        h, w = d["resolution"]
        doc.p(
            f"Render speed {d['fps']:.2f} FPS (median of {d['fps_repeats']}) for a {w}×{h} panorama, "
            f"backend {d['backend']} on {d['device']}, {d['threads']} torch threads, "
            f"{d['num_gaussians']:,} Gaussians; evaluated at {w}×{h} on the {d['split']} split."
        )

        # -- per view
        doc.h(2, "Views: ground truth / render / error / depth", "views")
        sections.append("views")
        edir = run_dir / "evaluate"
        from evaluation.visuals import ERROR_VMAX

        for v in d["views"]:
            doc.h(3, f"{v['view']} — PSNR {v['psnr']:.2f} dB, SSIM {v['ssim']:.3f}")
            items = [(edir / v["gt"], "ground truth"), (edir / v["render"], "render"),
                     (edir / v["error"], f"|error| (0 … {ERROR_VMAX})"), (edir / v["depth"], "depth")]
            items = [(pth, c) for pth, c in items if pth.is_file()]
            doc.images(items, f"view-{v['view']}")

    # -- training curves
    tr = read_artifact(run_dir, "train")
    doc.h(2, "Training", "training")
    if tr is None:
        doc.p("No training artifact: run `pano-pipe run train SCENE`.", "warn")
    else:
        td = tr["data"]
        summary = [
            ["iterations", _fmt(td.get("iterations"))], ["Gaussians", _fmt(td.get("num_gaussians"))],
            ["training seconds", _fmt(td.get("train_seconds"))],
            ["resolution (H×W)", "×".join(str(x) for x in td.get("resolution", []))],
            ["init", _fmt(td.get("init"))], ["projection", _fmt(td.get("projection"))],
            ["layout regularisation", _fmt(td.get("layout_reg"))], ["λ layout", _fmt(td.get("lambda_layout"))],
            ["preset", _fmt(td.get("preset"))], ["backend", _fmt(td.get("backend"))],
            ["final train PSNR", _fmt(td.get("final_train_psnr"))],
        ]
        doc.table(["setting", "value"], summary)
        series = training_series(read_jsonl(run_dir / "train" / td.get("log", "train_log.jsonl")))
        curves = img_dir / "training_curves.png"
        if plot_training_curves(series, curves):
            sections.append("training")
            doc.images([(curves, "training curves: against iteration (top) and wall time (bottom)")], "training")
        else:
            doc.p("The training log holds no loss / PSNR / Gaussian-count records.", "warn")

    # -- floor plan
    doc.h(2, "Floor plan and cameras", "floorplan")
    un = read_artifact(run_dir, "union")
    plan = img_dir / "floor_plan.png"
    drawn = False
    if un is not None and (run_dir / "union" / un["data"].get("drawing", "floor_plan.png")).is_file():
        shutil.copyfile(run_dir / "union" / un["data"]["drawing"], plan)
        area = un["data"].get("area_m2")
        doc.p(f"Merged floor plan from the union stage ({_fmt(area)} m²) with the camera positions.")
        drawn = True
    elif draw_floor_plan_fallback(scene, plan):
        doc.p("No union artifact (layout skipped or not run): cameras from the scene's poses, "
              "over the ground-truth rooms where the scene has them.", "note")
        drawn = True
    if drawn:
        sections.append("floorplan")
        doc.images([(plan, "floor plan with cameras")], "floorplan")
    else:
        doc.p("No floor plan: run the union stage.", "warn")

    # -- durations
    doc.h(2, "Stage durations", "durations")
    rows = stage_durations(run_dir)
    if rows:
        sections.append("durations")
        header = ["stage", "last run (s)", "runs logged", "total logged (s)", "status", "warnings"]
        body = [[r["stage"], _fmt(r["duration_s"]), str(r["runs"]), _fmt(r["total_s"]), r["status"], str(r["warnings"])]
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
    for sub, name, title in (("ablate", "ablation", "Ablation"), ("sweep", "sweep", "Accuracy vs cost sweep")):
        doc_json = run_dir / sub / f"{name}.json"
        chart = run_dir / sub / f"{name}.png"
        if not (doc_json.is_file() and chart.is_file()):
            continue
        doc.h(2, title, sub)
        sections.append(sub)
        md_file = run_dir / sub / f"{name}.md"
        table = [ln for ln in md_file.read_text().splitlines() if ln.startswith("|")] if md_file.is_file() else []
        if len(table) > 2:
            cells = [[c.strip() for c in ln.strip("|").split("|")] for ln in table]
            doc.table(cells[0], cells[2:])
        try:
            for note in json.loads(doc_json.read_text()).get("notes", []):
                doc.p(note)
        except ValueError:
            pass
        doc.images([(chart, f"{name} ({sub}/{name}.md)")], sub)

    out_dir.mkdir(parents=True, exist_ok=True)
    page = (
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
        f"<title>pano-pipe report: {html.escape(name)}</title><style>{_CSS}</style></head><body>\n"
        + "\n".join(doc.html)
        + "\n</body></html>\n"
    )
    html_path = out_dir / "report.html"
    md_path = out_dir / "report.md"
    html_path.write_text(page, encoding="utf-8")
    md_path.write_text("\n".join(doc.md).lstrip() + "\n", encoding="utf-8")
    return ReportPaths(html_path, md_path, out_dir, sections)
