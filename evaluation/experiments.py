"""`pano-pipe ablate` and `pano-pipe sweep`: many pipeline runs that share their upstream stages.

Each variant is an ordinary pipeline run (pipeline.engine.Engine) in its own
sub-folder of the scene's run folder, with train/evaluate parameters
overridden. The stages upstream of training (layout, depth, union, sampling,
align) are computed once in the main run folder and copied into each variant
folder; their cache keys do not depend on the train parameters, so the
variant's engine finds them up to date and runs only train and evaluate.

ablate: the paper's grid (Bai et al., Table 4), each with N seeds:
  1. 3D-GS*          random init, perspective crops (the paper's eight 120° crops; or the
                     cubemap), no layout regularisation
  2. + layout init   layout(+depth) point cloud init
  3. + 360 splatting direct equirectangular rendering instead of the crops
  4. + layout reg    the layout regulariser
`--paper` runs it at the paper's setting (the `paper` preset: 512×1024, 7k iterations; 3 seeds).
sweep: iterations × training resolution × Gaussian cap → PSNR against
training seconds and against render FPS, with the Pareto front.
"""

from __future__ import annotations

import json
import math
import types
import shutil
from dataclasses import asdict, dataclass, field
from itertools import product
from pathlib import Path

import numpy as np

from runfs.errors import PanoError
from runfs.paths import RUN_MARKER, run_path

# Paper's ablation on one Matterport3D scene, 4 views (DESIGN.md), for context in the table.
PAPER_PSNR = {"3D-GS*": 13.64, "+ layout init": 15.98, "+ 360 splatting": 16.66, "+ layout reg": 17.72}


def ablation_variants(baseline: str = "crops") -> list[tuple[str, str, dict]]:
    """Semantic settings of each ablation step (mapped onto the train stage's parameter names below);
    `baseline` is the projection of the 3D-GS* steps: 'crops' (the paper's) or 'cubemap'."""
    if baseline not in ("crops", "cubemap"):
        raise PanoError("--baseline", f"must be 'crops' or 'cubemap', got {baseline!r}")
    return [
        ("3dgs", "3D-GS*", {"init": "random", "projection": baseline, "layout_reg": False}),
        ("layout-init", "+ layout init", {"init": "layout", "projection": baseline, "layout_reg": False}),
        ("360", "+ 360 splatting", {"init": "layout", "projection": "360", "layout_reg": False}),
        ("layout-reg", "+ layout reg", {"init": "layout", "projection": "360", "layout_reg": True}),
    ]


VARIANTS = ablation_variants()
#: The paper's ablation setting (`ablate --paper`): its preset (512×1024, 7k iterations) and seeds.
PAPER_SEEDS = 3

#: The train-stage parameter of a semantic setting, where the names differ (else the same name).
TRAIN_PARAM = {"resolution": "height"}

MAIN_STAGES = ("train", "evaluate")


def train_param_fields() -> dict:
    from stages import train

    return dict(train.Params.model_fields)


def map_train_overrides(settings: dict, fields: dict | None = None) -> tuple[dict, list[str]]:
    """Semantic settings -> train-stage parameters; also the settings the stage has no parameter for."""
    fields = train_param_fields() if fields is None else fields
    out, missing = {}, []
    for key, value in settings.items():
        name = TRAIN_PARAM.get(key, key)
        if name not in fields:
            missing.append(key)
            continue
        if key == "init" and value == "layout":
            value = _layout_init_value(fields[name])
        out[name] = value
    return out, missing


def _layout_init_value(field_info) -> str:
    """The stage's name for 'initialise from the layout prior': 'auto' resolves to the best
    available cloud (layout + aligned depth), else 'layout+depth', else 'layout'."""
    import typing

    choices = [a for a in typing.get_args(field_info.annotation) if isinstance(a, str)]
    for c in ("auto", "layout+depth", "layout"):
        if c in choices:
            return c
    return "layout"


def resolution_value(height: int, field_info) -> object:
    """A training-resolution override in the form the stage's parameter takes (an int height or [H, W])."""
    import typing

    ann = field_info.annotation
    # Union members (X | None) or the annotation itself; a tuple/list member means [H, W].
    members = typing.get_args(ann) if typing.get_origin(ann) in (typing.Union, types.UnionType) else (ann,)
    if any(typing.get_origin(a) in (tuple, list) or a in (tuple, list) for a in members):
        return [int(height), 2 * int(height)]
    return int(height)


# ----------------------------------------------------------------------------- running variants


def prepare_variant_dir(base_dir: Path, variant_dir: Path, stages: list[str]) -> None:
    """Copy the shared upstream stage folders into a variant folder, replacing stale copies."""
    from pipeline.engine import read_meta

    variant_dir.mkdir(parents=True, exist_ok=True)
    if (base_dir / RUN_MARKER).is_file():  # a run folder of the same scene, made by pano-pipe
        shutil.copyfile(base_dir / RUN_MARKER, variant_dir / RUN_MARKER)
    for s in stages:
        src = base_dir / s
        if not (src / "artifact.json").is_file():
            continue  # skipped stage
        dst = variant_dir / s
        if dst.exists():
            copied, shared = read_meta(dst), read_meta(src)
            if copied is not None and shared is not None and copied.key == shared.key:
                continue
            shutil.rmtree(dst)
        shutil.copytree(src, dst)


def upstream_stages(registry) -> list[str]:
    from pipeline.engine import ancestors

    return [s for s in registry if s in ancestors(registry, "train")]


def merged_config(base: dict, train: dict, evaluate: dict | None = None) -> dict:
    cfg = {k: dict(v) for k, v in base.items()}
    cfg.setdefault("train", {}).update(train)
    if evaluate:
        cfg.setdefault("evaluate", {}).update(evaluate)
    return cfg


def run_variant(scene, base_dir: Path, variant_dir: Path, config: dict) -> dict:
    """Run train + evaluate for one variant (upstream copied from base_dir); returns its summary."""
    from pipeline.engine import Engine
    from pipeline.registry import build_registry

    reg = build_registry()
    # Bring the shared upstream stages up to date first (a no-op when cached): copies of a
    # stale base would only be recomputed in every variant folder.
    Engine(scene, base_dir, reg, config, config_source="experiment config").run(until="align")
    prepare_variant_dir(base_dir, variant_dir, upstream_stages(reg))
    engine = Engine(scene, variant_dir, reg, config, config_source="experiment config")
    results = engine.run()  # a variant already trained with these settings is cached
    return summarise_run(variant_dir, results)


def summarise_run(run_dir: Path, results=None) -> dict:
    from pipeline.engine import read_output

    ev, tr = read_output(run_dir, "evaluate"), read_output(run_dir, "train")
    if ev is None or tr is None:
        raise PanoError(run_dir, "variant run finished without train/evaluate artifacts")
    mean = ev.mean
    ran = {r.name: r.outcome for r in results} if results else {}
    return {
        "dir": str(run_dir),
        **{k: mean.get(k) for k in ("psnr", "psnr_colorfit", "ssim", "ws_psnr", "lpips", "depth_abs_rel",
                                   "flat_psnr", "flat_ssim")},
        **tr.model_dump(mode="json",
                        include={"train_seconds", "num_gaussians", "iterations", "train_images"}),
        "pixels_per_image": tr.crops.size ** 2 if tr.crops else tr.resolution[0] * tr.resolution[1],
        **ev.model_dump(mode="json", include={"fps", "split", "stitched"}),
        "eval_resolution": list(ev.resolution),
        "train": tr.model_dump(mode="json", include={"init", "projection", "layout_reg", "iterations",
                                                     "resolution", "preset", "appearance"}),
        "cached": ran.get("train") == "cached",
    }


def mean_std(values: list[float]) -> tuple[float, float]:
    vals = [v for v in values if v is not None and not math.isnan(v)]
    if not vals:
        return math.nan, math.nan
    return float(np.mean(vals)), float(np.std(vals, ddof=1)) if len(vals) > 1 else 0.0


# ----------------------------------------------------------------------------- ablation


@dataclass
class AblationRow:
    key: str
    label: str
    settings: dict
    runs: list[dict] = field(default_factory=list)

    def stat(self, metric: str) -> tuple[float, float]:
        return mean_std([r.get(metric) for r in self.runs])


def step_gain(prev: AblationRow, cur: AblationRow, metric: str = "psnr") -> tuple[float, float]:
    """(mean gain of `cur` over `prev`, its spread): the spread is the standard deviation of the
    difference of two independent runs, √(s_prev² + s_cur²) from the seeds' standard deviations."""
    (a, sa), (b, sb) = prev.stat(metric), cur.stat(metric)
    return b - a, math.hypot(sa, sb)


def ordering_notes(rows: list[AblationRow]) -> list[str]:
    """One line per step: does it beat the previous step on mean PSNR (the paper's claim), and by
    more than its spread?"""
    notes = []
    for prev, cur in zip(rows, rows[1:]):
        d, spread = step_gain(prev, cur)
        n = min(len(prev.runs), len(cur.runs))
        if math.isnan(d):
            notes.append(f"{cur.label}: no PSNR to compare")
        elif d > 0:
            extra = ("" if n < 2 else f", more than its spread {spread:.2f} dB" if d > spread else
                     f", within its spread {spread:.2f} dB over {n} seeds: not a clear gain")
            notes.append(f"✓ {cur.label} improves on {prev.label} by {d:+.2f} dB{extra}")
        else:
            notes.append(f"✗ {cur.label} does NOT improve on {prev.label}: {d:+.2f} dB"
                         + (f" (spread {spread:.2f} dB)" if n >= 2 else ""))
    return notes


TABLE_METRICS = (("psnr", 2), ("ssim", 3), ("ws_psnr", 2), ("lpips", 3), ("psnr_colorfit", 2))
TABLE_COSTS = (("iterations", 0), ("train_images", 0), ("train_seconds", 0), ("num_gaussians", 0))


def ablation_table(rows: list[AblationRow]) -> str:
    """Mean ± std over the seeds; the step's PSNR gain over the row above and whether it exceeds its
    spread; what each variant cost (iterations = optimiser steps, one training image each; the
    training images: panoramas, or their crops; training seconds; final Gaussians)."""
    lines = [
        "| variant | PSNR (dB) | SSIM | WS-PSNR (dB) | LPIPS | PSNR colour-fit (dB) | gain (dB) | > spread | "
        "iterations | train images | train s | Gaussians | paper PSNR |",
        "|" + "---|" * 13,
    ]
    for i, r in enumerate(rows):
        cells = []
        for m, d in TABLE_METRICS:
            mu, sd = r.stat(m)
            cells.append("—" if math.isnan(mu) else f"{mu:.{d}f} ± {sd:.{d}f}")
        gain, spread = step_gain(rows[i - 1], r) if i else (math.nan, math.nan)
        cells.append("—" if math.isnan(gain) else f"{gain:+.2f} (± {spread:.2f})")
        cells.append("—" if math.isnan(gain) or min(len(r.runs), len(rows[i - 1].runs)) < 2
                     else ("yes" if gain > spread else "no"))
        for m, d in TABLE_COSTS:
            mu, sd = r.stat(m)
            cells.append("—" if math.isnan(mu) else f"{mu:.{d}f}" if sd == 0 else f"{mu:.{d}f} ± {sd:.{d}f}")
        lines.append(f"| {r.label} | " + " | ".join(cells) + f" | {PAPER_PSNR.get(r.label, '—')} |")
    return "\n".join(lines)


def plot_ablation(rows: list[AblationRow], path: Path) -> None:
    from evaluation.visuals import pyplot

    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.5, 3.8))
    x = np.arange(len(rows))
    mus = [r.stat("psnr")[0] for r in rows]
    sds = [r.stat("psnr")[1] for r in rows]
    ax.bar(x, mus, yerr=sds, capsize=5, color=["C7", "C0", "C1", "C2"][: len(rows)], label="this run")
    for i, r in enumerate(rows):
        for run in r.runs:
            ax.plot(i, run["psnr"], "k.", ms=4)
        if not math.isnan(mus[i]):
            ax.text(i, mus[i], f"{mus[i]:.2f}\n", ha="center", va="bottom", fontsize=8)
    paper = [PAPER_PSNR.get(r.label, np.nan) for r in rows]
    ax.plot(x, paper, "r_", ms=30, mew=2, label="paper (Matterport3D)")
    ax.set_xticks(x, [r.label for r in rows], fontsize=8)
    ax.set_ylabel("test PSNR (dB)")
    finite = [v for v in mus + paper if not math.isnan(v)]
    if finite:
        ax.set_ylim(max(0.0, min(finite) - 3), max(finite) + 2)
    ax.legend(fontsize=8, loc="upper left")
    ax.set_title("ablation (mean ± std over seeds)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def paper_config(base_config: dict) -> dict:
    """The paper's setting under `base_config`: the train stage's `paper` preset (512×1024
    training, 7k iterations, its densification budget) and evaluation at the training size;
    settings given explicitly (--config/--set) still win."""
    cfg = {k: dict(v) for k, v in base_config.items()}
    cfg.setdefault("train", {}).setdefault("preset", "paper")
    cfg.setdefault("evaluate", {}).setdefault("resolution", "train")
    return cfg


def run_ablation(scene, base_dir: Path, base_config: dict, seeds: int = 1, iterations: int | None = None,
                 variants=None, out_dir: Path | None = None, log=print, baseline: str = "crops",
                 command: str | None = None, equal: str = "time") -> dict:
    """Run the ablation grid; writes ablation.{md,json,png} into out_dir (default <run>/ablate/).
    `command` (the command line) is written into ablation.md. `equal` (EQUAL_BUDGETS): after the
    grid, the cheaper of the two projection rows (PROJECTION_PAIR) is trained again with as many
    iterations as the other's budget buys (time or pixels), and both comparisons are tabled."""
    from pipeline.engine import Engine
    from pipeline.registry import build_registry

    if seeds < 1:
        raise PanoError("--seeds", "must be at least 1")
    if equal not in EQUAL_BUDGETS:
        raise PanoError("--equal", f"must be one of {', '.join(EQUAL_BUDGETS)}, got {equal!r}")
    variants = ablation_variants(baseline) if variants is None else variants
    out_dir = Path(out_dir) if out_dir is not None else run_path(base_dir, "ablate")
    reg = build_registry()
    fields = train_param_fields()
    # The shared upstream stages, once, in the main run folder (cached if already there);
    # first, so that a new base folder is made (and marked) as a run folder.
    Engine(scene, base_dir, reg, base_config, config_source="config").run(until="align")
    out_dir.mkdir(parents=True, exist_ok=True)

    rows, warnings = [], []

    def run_row(key: str, label: str, settings: dict, iterations: int | None) -> AblationRow:
        extra = dict(settings)
        if iterations is not None:
            extra["iterations"] = iterations
        row = AblationRow(key, label, settings)
        for seed in range(seeds):
            overrides, missing = map_train_overrides({**extra, "seed": seed}, fields)
            if missing:
                msg = f"the train stage has no parameter for {missing}; variant {label!r} cannot set them"
                if msg not in warnings:
                    warnings.append(msg)
                    log(f"warning: {msg}")
            cfg = merged_config(base_config, overrides, {"fps_repeats": 2})
            log(f"ablate: {label} seed {seed} → {out_dir / f'{key}-s{seed}'}")
            summary = run_variant(scene, base_dir, out_dir / f"{key}-s{seed}", cfg)
            summary["seed"] = seed
            got = summary["train"].get("init")
            if settings.get("init") != "random" and got == "random":
                msg = (f"variant {label!r} wanted a layout initialisation but the train stage used 'random' "
                       "(the scene has no layout / the upstream stages were skipped): its row is not an ablation step")
                if msg not in warnings:
                    warnings.append(msg)
                    log(f"warning: {msg}")
            row.runs.append(summary)
        return row

    for key, label, settings in variants:
        rows.append(run_row(key, label, settings, iterations))
    plan = equal_budget_plan(rows, equal)
    equal_row = None
    if plan is not None:
        cheap, n_iter, ratio = plan
        log(f"ablate: equal {equal}: {cheap.label} costs {ratio:.2f}x less per iteration -> {n_iter} iterations")
        equal_row = run_row(f"{cheap.key}-equal-{equal}", f"{cheap.label} (equal {equal})", cheap.settings, n_iter)

    notes = ordering_notes(rows)
    table = ablation_table(rows)
    proj_table, proj_notes = projection_table(rows, equal_row, equal)
    notes += proj_notes
    plot_ablation(rows, out_dir / "ablation.png")
    split = {r["split"] for row in rows for r in row.runs}
    md = [f"# Ablation: {scene.name}", ""]
    if command:
        md += [f"`{command}`", ""]
    md += [setting_line(rows, seeds, iterations, split, scene), "", table, ""]
    if proj_table:
        md += ["Projection at equal budgets (" + (f"equal {equal}: the cheaper projection trained for as many "
               "iterations as the other's budget buys" if equal_row is not None else "equal iterations only") +
               "):", "", proj_table, ""]
    md += [*[f"- {n}" for n in notes]]
    if warnings:
        md += ["", *[f"> warning: {w}" for w in warnings]]
    md += ["", "![ablation](ablation.png)", ""]
    (out_dir / "ablation.md").write_text("\n".join(md))
    def row_doc(r: AblationRow) -> dict:
        return {"key": r.key, "label": r.label, "settings": r.settings,
                **{m: dict(zip(("mean", "std"), r.stat(m))) for m, _ in TABLE_METRICS + TABLE_COSTS},
                "paper_psnr": PAPER_PSNR.get(r.label), "runs": r.runs}

    doc = {
        "scene": scene.name, "seeds": seeds, "iterations": iterations, "command": command, "notes": notes,
        "warnings": warnings, "variants": [row_doc(r) for r in rows],
        "equal_budget": {"budget": equal, "row": None if equal_row is None else row_doc(equal_row),
                         "table": proj_table},
    }
    (out_dir / "ablation.json").write_text(json.dumps(doc, indent=1, default=_json_default))
    return {"table": table, "notes": notes, "markdown": out_dir / "ablation.md", "json": out_dir / "ablation.json",
            "chart": out_dir / "ablation.png", "rows": rows, "equal_row": equal_row, "projection_table": proj_table}

# ----------------------------------------------------------------------------- equal budget

#: How `ablate` puts the two projections on an equal footing beyond equal iterations: "time" (the
#: same training wall time, from the equal-iteration runs' seconds per iteration), "pixels" (the
#: same number of training pixels rendered: a crop has fewer than a panorama) or "none".
EQUAL_BUDGETS = ("time", "pixels", "none")
#: The two rows the projection comparison is about: the baseline with layout init, and the 360 row.
PROJECTION_PAIR = ("layout-init", "layout-reg")


def cost_per_iteration(run: dict, budget: str) -> float | None:
    """What one iteration of `run` costs under `budget`: training seconds, or pixels rendered."""
    if budget == "time":
        t, it = run.get("train_seconds"), run.get("iterations")
        return t / it if t and it else None
    if budget == "pixels":
        return run.get("pixels_per_image")
    raise ValueError(budget)


def equal_budget_plan(rows: list[AblationRow], budget: str) -> tuple[AblationRow, int, float] | None:
    """(the cheaper row of PROJECTION_PAIR, the iterations it gets at the other's budget, the cost
    ratio) or None when there is nothing to compare (a row missing, costs unknown, equal costs)."""
    if budget == "none":
        return None
    pair = {r.key: r for r in rows if r.key in PROJECTION_PAIR}
    if len(pair) != 2 or any(not r.runs for r in pair.values()):
        return None
    cost = {}
    for k, r in pair.items():
        c = [cost_per_iteration(run, budget) for run in r.runs]
        if any(v is None for v in c):
            return None
        cost[k] = float(np.mean(c))
    cheap, dear = sorted(PROJECTION_PAIR, key=lambda k: cost[k])
    ratio = cost[dear] / cost[cheap]
    if ratio < 1.05:  # within 5 %: equal iterations already are an equal budget
        return None
    iters = float(np.mean([run["iterations"] for run in pair[dear].runs]))
    return pair[cheap], int(round(iters * ratio)), ratio


def projection_table(rows: list[AblationRow], extra: AblationRow | None, budget: str) -> tuple[str, list[str]]:
    """The projection comparison (baseline + layout init against 360 + layout reg) at equal iterations
    and, with `extra` (the cheaper projection rerun at the other's budget), at equal `budget`;
    returns (markdown table, notes)."""
    pair = {r.key: r for r in rows if r.key in PROJECTION_PAIR}
    if len(pair) != 2:
        return "", []
    base, p360 = pair[PROJECTION_PAIR[0]], pair[PROJECTION_PAIR[1]]
    lines = ["| budget | " + f"{base.label} PSNR / SSIM | {p360.label} PSNR / SSIM | iterations (base / 360) | "
             "train s (base / 360) | 360 − base PSNR (dB) | 360 − base SSIM |", "|" + "---|" * 7]
    notes = []
    settings = [("equal iterations", base, p360)]
    if extra is not None:
        settings.append((f"equal {budget}", extra if extra.settings["projection"] != "360" else base,
                         extra if extra.settings["projection"] == "360" else p360))
    for name, b, t in settings:
        (pb, sb), (pt, st) = b.stat("psnr"), t.stat("psnr")
        (qb, qsb), (qt, qst) = b.stat("ssim"), t.stat("ssim")
        dp, sp = pt - pb, math.hypot(sb, st)
        dq, sq = qt - qb, math.hypot(qsb, qst)
        n = min(len(b.runs), len(t.runs))
        lines.append(
            f"| {name} | {pb:.2f} / {qb:.3f} | {pt:.2f} / {qt:.3f} | {b.stat('iterations')[0]:.0f} / "
            f"{t.stat('iterations')[0]:.0f} | {b.stat('train_seconds')[0]:.0f} / {t.stat('train_seconds')[0]:.0f} | "
            f"{dp:+.2f} (± {sp:.2f}) | {dq:+.3f} (± {sq:.3f}) |")
        verdict = ("beats" if dp > sp and dq > sq else "does not clearly beat") if n >= 2 else \
            ("beats" if dp > 0 and dq > 0 else "does not beat")
        notes.append(f"{'✓' if verdict == 'beats' else '✗'} at {name}, 360 {verdict} {base.settings['projection']}: "
                     f"{dp:+.2f} dB PSNR (spread {sp:.2f}), {dq:+.3f} SSIM (spread {sq:.3f})")
    return "\n".join(lines), notes



def setting_line(rows: list[AblationRow], seeds: int, iterations: int | None, split: set, scene) -> str:
    """One sentence of what was run: seeds, resolutions, preset, iterations, appearance, masks, baseline."""
    first = rows[0].runs[0] if rows and rows[0].runs else {}
    tr = first.get("train", {})
    res, ev = tr.get("resolution"), first.get("eval_resolution")
    nadir = getattr(getattr(scene, "manifest", None), "nadir_mask_deg", 0) or 0
    parts = [f"{seeds} seed(s) per variant",
             f"training {res[0]}×{res[1]}" if res else None, f"evaluation {ev[0]}×{ev[1]}" if ev else None,
             f"preset {tr.get('preset')}" if tr.get("preset") else None,
             f"iterations {iterations or tr.get('iterations') or 'stage default'}",
             f"appearance {'on' if tr.get('appearance') else 'off'}",
             f"nadir mask {nadir:g}°" if nadir else "no nadir mask",
             f"3D-GS* test panoramas stitched from {first['stitched']}" if first.get("stitched") else None,
             f"metrics on the {'/'.join(sorted(split))} split (valid pixels)"]
    return "; ".join(p for p in parts if p) + "."


def _json_default(o):
    if isinstance(o, float) and math.isnan(o):
        return None
    if isinstance(o, Path):
        return str(o)
    return str(o)


# ----------------------------------------------------------------------------- sweep


@dataclass
class SweepPoint:
    iterations: int
    height: int
    cap: int | None
    psnr: float | None = None
    ssim: float | None = None
    ws_psnr: float | None = None
    train_seconds: float | None = None
    fps: float | None = None
    num_gaussians: int | None = None
    pareto_time: bool = False
    pareto_fps: bool = False
    dir: str = ""

    @property
    def label(self) -> str:
        return f"it{self.iterations}-h{self.height}-cap{self.cap if self.cap is not None else 'default'}"


def pareto_mask(quality: list[float], cost: list[float]) -> list[bool]:
    """True where no other point has quality ≥ and cost ≤ with one of them strict (higher quality,
    lower cost are better)."""
    n = len(quality)
    out = []
    for i in range(n):
        dominated = any(
            quality[j] >= quality[i] and cost[j] <= cost[i] and (quality[j] > quality[i] or cost[j] < cost[i])
            for j in range(n) if j != i
        )
        out.append(not dominated)
    return out


def parse_grid(text: str, kind=int, allow_none: bool = False) -> list:
    vals = []
    for tok in (t.strip() for t in str(text).split(",") if t.strip()):
        if allow_none and tok.lower() in ("none", "default"):
            vals.append(None)
            continue
        try:
            v = kind(tok)
        except ValueError:
            raise PanoError("sweep", f"{tok!r} is not a number in {text!r}") from None
        if v <= 0:
            raise PanoError("sweep", f"{tok!r} must be positive in {text!r}")
        vals.append(v)
    if not vals:
        raise PanoError("sweep", f"empty grid {text!r}")
    return vals


def plot_sweep(points: list[SweepPoint], path: Path) -> None:
    from evaluation.visuals import pyplot

    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    pts = [p for p in points if p.psnr is not None]
    for ax, attr, flag, xlabel in (
        (axes[0], "train_seconds", "pareto_time", "training seconds"),
        (axes[1], "fps", "pareto_fps", "render FPS (evaluation size)"),
    ):
        xs = [getattr(p, attr) for p in pts]
        ys = [p.psnr for p in pts]
        ax.scatter(xs, ys, c="C0", s=25, zorder=3)
        front = sorted((getattr(p, attr), p.psnr) for p in pts if getattr(p, flag))
        if front:
            ax.plot(*zip(*front), "C3-", lw=1.5, zorder=2, label="Pareto front")
        for p in pts:
            ax.annotate(p.label, (getattr(p, attr), p.psnr), fontsize=6, xytext=(3, 3), textcoords="offset points")
        if xs and min(xs) > 0 and max(xs) / min(xs) > 20:
            ax.set_xscale("log")
        ax.set_xlabel(xlabel)
        ax.set_ylabel("test PSNR (dB)")
        ax.grid(alpha=0.3)
        if front:
            ax.legend(fontsize=8)
    axes[0].set_title("accuracy vs training time")
    axes[1].set_title("accuracy vs render speed")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def sweep_table(points: list[SweepPoint]) -> str:
    lines = ["| iterations | train height | Gaussian cap | PSNR (dB) | SSIM | train s | FPS | Gaussians | Pareto (time / FPS) |",
             "|---|---|---|---|---|---|---|---|---|"]

    def f(v, d):
        return "—" if v is None else f"{v:.{d}f}"

    for p in sorted(points, key=lambda p: (p.train_seconds or 0)):
        lines.append(
            f"| {p.iterations} | {p.height} | {p.cap if p.cap is not None else 'default'} | {f(p.psnr, 2)} | "
            f"{f(p.ssim, 3)} | {f(p.train_seconds, 1)} | {f(p.fps, 2)} | {p.num_gaussians or '—'} | "
            f"{'★' if p.pareto_time else '·'} / {'★' if p.pareto_fps else '·'} |"
        )
    return "\n".join(lines)


def run_sweep(scene, base_dir: Path, base_config: dict, iterations: list[int], heights: list[int],
              caps: list[int | None], eval_height: int | None = None, out_dir: Path | None = None,
              log=print) -> dict:
    """Train/evaluate every grid point; all points are evaluated at one size (default: the largest
    training height) so their PSNR and FPS compare. Writes sweep.{md,json,png}."""
    from pipeline.engine import Engine
    from pipeline.registry import build_registry

    out_dir = Path(out_dir) if out_dir is not None else run_path(base_dir, "sweep")
    reg = build_registry()
    fields = train_param_fields()
    res_name = TRAIN_PARAM["resolution"]
    if res_name not in fields:
        raise PanoError("sweep", f"the train stage has no resolution parameter {res_name!r}")
    eh = int(eval_height or max(heights))
    Engine(scene, base_dir, reg, base_config, config_source="config").run(until="align")
    out_dir.mkdir(parents=True, exist_ok=True)
    points = []
    for it, h, cap in product(iterations, heights, caps):
        p = SweepPoint(it, h, cap)
        # cap None: leave the train stage's own (preset) cap in place
        wanted = {"iterations": it} | ({"max_gaussians": cap} if cap is not None else {})
        overrides, missing = map_train_overrides(wanted, fields)
        if missing:
            raise PanoError("sweep", f"the train stage has no parameter for {missing}")
        overrides[res_name] = resolution_value(h, fields[res_name])
        cfg = merged_config(base_config, overrides, {"resolution": [eh, 2 * eh], "fps_repeats": 3})
        log(f"sweep: {p.label} → {out_dir / p.label}")
        s = run_variant(scene, base_dir, out_dir / p.label, cfg)
        p.psnr, p.ssim, p.ws_psnr = s["psnr"], s["ssim"], s["ws_psnr"]
        p.train_seconds, p.fps, p.num_gaussians, p.dir = s["train_seconds"], s["fps"], s["num_gaussians"], s["dir"]
        points.append(p)
    done = [p for p in points if p.psnr is not None]
    for p, a, b in zip(done, pareto_mask([p.psnr for p in done], [p.train_seconds for p in done]),
                       pareto_mask([p.psnr for p in done], [-p.fps for p in done])):
        p.pareto_time, p.pareto_fps = a, b
    table = sweep_table(points)
    plot_sweep(points, out_dir / "sweep.png")
    md = [f"# Sweep: {scene.name}", "",
          f"Every point evaluated at {eh}×{2 * eh}; ★ = on the Pareto front (no other point is both "
          "more accurate and cheaper).", "", table, "", "![sweep](sweep.png)", ""]
    (out_dir / "sweep.md").write_text("\n".join(md))
    (out_dir / "sweep.json").write_text(json.dumps(
        {"scene": scene.name, "eval_resolution": [eh, 2 * eh], "points": [asdict(p) | {"label": p.label} for p in points]},
        indent=1, default=_json_default))
    return {"table": table, "markdown": out_dir / "sweep.md", "json": out_dir / "sweep.json",
            "chart": out_dir / "sweep.png", "points": points}
