"""The 360-vs-crops study of docs/training.md ("Sparse captures: 360° against crops").

Trains and evaluates variants of the train stage on one scene (the upstream stages computed once in
--base), N seeds each, and appends one JSON line per run to --out, so an interrupted study keeps
what it measured and a rerun skips what is already there. `--table` prints the markdown table
(mean ± std over seeds) of the lines in --out.

    PYTHONPATH=$PWD .venv/bin/python scripts/study_360.py SCENE --base RUN_DIR --out study.jsonl \
        --variant crops --variant 360 --seeds 3 --set train.appearance=true
    PYTHONPATH=$PWD .venv/bin/python scripts/study_360.py SCENE --out study.jsonl --table

A variant is a name from VARIANTS, or NAME:param=value,param=value (train-stage parameters).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import yaml

#: Named variants: train-stage overrides on top of the layout init (init auto).
VARIANTS: dict[str, dict] = {
    "crops": {"projection": "crops", "layout_reg": False},
    "crops+reg": {"projection": "crops", "layout_reg": True},
    "360": {"projection": "360", "layout_reg": False},
    "360+reg": {"projection": "360", "layout_reg": True},
}

#: (record key, decimals, table heading); flat_*: evaluate's flat image of the training mean colour, the floor
METRICS = (("psnr", 2, "PSNR"), ("ssim", 3, "SSIM"), ("ws_psnr", 2, "WS-PSNR"), ("psnr_colorfit", 2, "colour-fit PSNR"),
           ("flat_psnr", 2, "flat PSNR"), ("flat_ssim", 3, "flat SSIM"), ("lpips", 3, "LPIPS"),
           ("num_gaussians", 0, "Gaussians"), ("train_seconds", 0, "train s"))


def parse_variant(text: str) -> tuple[str, dict]:
    if text in VARIANTS:
        return text, dict(VARIANTS[text])
    name, _, rest = text.partition(":")
    base, _, _ = name.partition("/")
    out = dict(VARIANTS.get(base, {}))
    for item in filter(None, rest.split(",")):
        k, _, v = item.partition("=")
        value = yaml.safe_load(v)
        out[k.strip()] = str(value) if k.strip() == "projection" else value  # "360" is a name, not a number
    return name, out


def parse_sets(items: list[str]) -> dict:
    cfg: dict = {}
    for item in items:
        key, _, v = item.partition("=")
        stage, _, param = key.partition(".")
        cfg.setdefault(stage, {})[param] = yaml.safe_load(v)
    return cfg


def done_runs(path: Path) -> list[dict]:
    if not path.is_file():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def table(runs: list[dict], reference: str | None = None) -> str:
    import numpy as np

    by: dict[str, list[dict]] = {}
    for r in runs:
        by.setdefault(r["variant"], []).append(r)
    head = "| variant | seeds | " + " | ".join(label for _, _, label in METRICS) + " | Δ PSNR vs " + (reference or "—") + " |"
    lines = [head, "|" + "---|" * (len(METRICS) + 3)]
    ref = by.get(reference or "", [])
    ref_mu = np.mean([r["psnr"] for r in ref]) if ref else math.nan
    ref_sd = np.std([r["psnr"] for r in ref], ddof=1) if len(ref) > 1 else 0.0
    for name, rs in by.items():
        cells = []
        for m, d, _ in METRICS:
            vals = [r[m] for r in rs if r.get(m) is not None]
            if not vals:
                cells.append("—")
                continue
            mu, sd = float(np.mean(vals)), float(np.std(vals, ddof=1)) if len(vals) > 1 else 0.0
            cells.append(f"{mu:.{d}f} ± {sd:.{d}f}")
        p = [r["psnr"] for r in rs]
        mu, sd = float(np.mean(p)), float(np.std(p, ddof=1)) if len(p) > 1 else 0.0
        delta = "—" if math.isnan(ref_mu) or name == reference else \
            f"{mu - ref_mu:+.2f} (spread {math.hypot(sd, ref_sd):.2f})"
        lines.append(f"| {name} | {len(rs)} | " + " | ".join(cells) + f" | {delta} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", type=Path)
    ap.add_argument("--base", type=Path, help="run folder holding the upstream stages (made if missing)")
    ap.add_argument("--out", type=Path, required=True, help="JSON lines, one per run (appended)")
    ap.add_argument("--variant", action="append", default=[])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--set", action="append", default=[], help="STAGE.PARAM=VALUE for every variant")
    ap.add_argument("--table", action="store_true", help="print the table of --out and exit")
    ap.add_argument("--reference", default="crops", help="variant the Δ column compares to")
    args = ap.parse_args(argv)

    if args.table:
        print(table(done_runs(args.out), args.reference))
        return 0

    from evaluation.experiments import merged_config, run_variant
    from schemas.scene_loader import load_scene

    scene = load_scene(args.scene)
    base = args.base or args.out.parent / "base"
    common = parse_sets(args.set)
    common.setdefault("evaluate", {}).setdefault("fps_repeats", 1)
    have = {(r["variant"], r["seed"], r["tag"]) for r in done_runs(args.out)}
    tag = json.dumps(common, sort_keys=True)
    for text in args.variant:
        name, overrides = parse_variant(text)
        for seed in range(args.first_seed, args.first_seed + args.seeds):
            if (name, seed, tag) in have:
                continue
            cfg = merged_config(common, {**common.get("train", {}), **overrides, "seed": seed},
                                common.get("evaluate"))
            vdir = args.out.parent / f"{args.out.stem}-runs" / f"{name.replace('/', '_')}-s{seed}"
            print(f"study: {name} seed {seed} -> {vdir}", flush=True)
            s = run_variant(scene, base, vdir, cfg)
            rec = {"variant": name, "seed": seed, "tag": tag, "overrides": overrides,
                   **{m: s.get(m) for m, _, _ in METRICS}, "dir": s["dir"]}
            with open(args.out, "a") as f:
                f.write(json.dumps(rec) + "\n")
            print(f"study: {name} seed {seed}: PSNR {s['psnr']:.2f} SSIM {s['ssim']:.3f} "
                  f"{s['num_gaussians']} G {s['train_seconds']:.0f} s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
