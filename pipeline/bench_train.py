"""``pano-pipe bench train``: iterations per second, seconds per part of the training step and
held-out PSNR of one training preset through the whole pipeline (the engine `pano-pipe run all`
drives), on the CPU or the GPU (``--device``): the figures docs/gpu.md and docs/benchmarks.md
compare.

``--against CHECKOUT`` runs the same bench on another checkout of pano-pipe (e.g. a git
worktree of an older commit) in the same run, alternately with this one, and prints the
ratio: absolute times on a shared machine vary from run to run, their ratio far less. Each
checkout runs in its own subprocess, importing its own code (and compiling its own kernel).
The stages before `train` run once per checkout; every repeat copies their run folder and
runs `train` and `evaluate` from there. ``--upstream RUN`` gives that folder instead (the stages
before train run elsewhere, e.g. where open3d is installed, and the GPU machine only trains).
"""

from __future__ import annotations

import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

import torch

from evaluation.report_text import fmt
from runfs.errors import PanoError
from runfs.fsutil import atomic_write_text

# Runs one step of the bench inside a checkout (argv: scene, run folder, config JSON, until or "").
# Plain engine calls that every version of pano-pipe with `train.iterations` understands.
_WORKER = r"""
import json, sys, time
from pathlib import Path
from pipeline.engine import Engine
from pipeline.registry import build_registry
try:  # where scene loading lives in this checkout's version
    from schemas.scene_loader import load_scene
except ImportError:
    from pipeline.scene_loader import load_scene
scene, run_dir, config, until = Path(sys.argv[1]), Path(sys.argv[2]), json.loads(sys.argv[3]), sys.argv[4] or None
t0 = time.perf_counter()
Engine(load_scene(scene), run_dir, build_registry(), config).run(until=until)
wall = time.perf_counter() - t0
art = {}
for name in ("train", "evaluate"):
    f = run_dir / name / "artifact.json"
    if f.is_file():
        a = json.loads(f.read_text())
        art[name] = a.get("data", a)
log = run_dir / "train" / "train_log.jsonl"  # (iteration, seconds, Gaussians) every log_every steps
if log.is_file():
    recs = [json.loads(line) for line in log.read_text().splitlines() if line.strip()]
    art["log"] = [[r["iteration"], r["seconds"], r["num_gaussians"]] for r in recs]
try:  # Triton's compiled variants (a GPU run; checkouts without the count skip it)
    from splatting.kernel_report import loaded_variants
    art["kernel_variants"] = loaded_variants()
except Exception:
    pass
print("BENCH-RESULT " + json.dumps({"wall": wall, **art}))
"""


def _run_in(checkout: Path, scene: Path, run_dir: Path, config: dict, until: str | None) -> dict:
    # the checkout first; what the caller's PYTHONPATH adds (e.g. carried wheels) stays reachable
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(filter(None, [str(checkout), os.environ.get("PYTHONPATH")])))
    proc = subprocess.run([sys.executable, "-c", _WORKER, str(scene), str(run_dir), json.dumps(config), until or ""],
                          cwd=checkout, env=env, capture_output=True, text=True)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("BENCH-RESULT ")]
    if proc.returncode != 0 or not lines:
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-1:] or ["no output"]
        raise PanoError(checkout, f"bench run failed: {tail[0]}")
    return json.loads(lines[-1].split(" ", 1)[1])


def _summary(res: dict) -> dict:
    train, evaluate = res.get("train", {}), res.get("evaluate", {})
    mean = evaluate.get("mean")
    return {
        "train_seconds": train.get("train_seconds"), "iterations": train.get("iterations"),
        "iterations_per_s": train["iterations"] / max(train["train_seconds"], 1e-9),
        "num_gaussians": train.get("num_gaussians"), "backend": train.get("backend"),
        "step_seconds": train.get("step_seconds"),
        "heldout_psnr": mean.get("psnr") if isinstance(mean, dict) else None,
        "render_fps": evaluate.get("fps"), "run_wall_s": res["wall"],
        "windows": _windows(res.get("log") or [], train.get("iterations") or 0),
        "kernel_variants": res.get("kernel_variants"),
    }


def _windows(log: list, iterations: int, parts: int = 7) -> list[dict]:
    """It/s over `parts` equal spans of the run, from the train log's (iteration, seconds,
    Gaussians) records: whether a slow run is slow throughout (the step) or in some spans
    (compiles, densification, the Gaussians' growth)."""
    if len(log) < 2 or iterations < parts:
        return []
    out, prev = [], log[0]
    for k in range(1, parts + 1):
        target = iterations * k // parts
        rec = min(log, key=lambda r: abs(r[0] - target))
        if rec[0] > prev[0] and rec[1] > prev[1]:
            out.append({"from": prev[0], "to": rec[0], "iterations_per_s": (rec[0] - prev[0]) / (rec[1] - prev[1]),
                        "gaussians": rec[2]})
            prev = rec
    return out


def bench_train(scene: Path | None, device: str, preset: str, height: int, out_md: Path, out_json: Path,
                iterations: int | None = None, against: Path | None = None, repeats: int = 1,
                this_overrides: dict | None = None, upstream: Path | None = None, log=print) -> dict:
    if device == "cuda" and not torch.cuda.is_available():
        raise PanoError("--device", "cuda asked for, but torch sees no CUDA device here (docs/gpu.md)")
    if against is not None and not (against / "pipeline" / "engine.py").is_file():
        raise PanoError(against, "not a pano-pipe checkout (no pipeline/engine.py)")
    if upstream is not None and (against is not None or scene is None):
        raise PanoError("--upstream", "needs the scene it was made from and no --against")
    if upstream is not None and not (upstream / "align" / "artifact.json").is_file():
        raise PanoError(upstream, "not a run folder with the stages before train (no align/artifact.json)")
    here = Path(__file__).resolve().parents[1]
    checkouts = {"this": here} if against is None else {"this": here, "other": against.resolve()}
    train_cfg = {"preset": preset, "device": device, "height": height}
    if iterations is not None:
        train_cfg["iterations"] = int(iterations)
    config = {"train": train_cfg, "evaluate": {"device": device}}
    configs = {name: config for name in checkouts}
    if this_overrides:  # e.g. an older checkout's defaults, so that both train the same way
        configs["this"] = dict(config)
        for stage, params in this_overrides.items():
            configs["this"][stage] = {**config.get(stage, {}), **params}
    runs: dict[str, list[dict]] = {k: [] for k in checkouts}
    with tempfile.TemporaryDirectory(prefix="pano-bench-train-") as tmp:
        if scene is None:
            import simulate

            scene = Path(tmp) / "demo"
            log(f"bench train: simulating the demo scene at {2 * height}x{height}")
            simulate.generate_scene(scene, preset="demo", height=height, with_layout=True, with_depth=True)
        prepared = {}
        for name, co in checkouts.items():  # the stages before train, once per checkout
            if upstream is not None:
                prepared[name] = upstream
                continue
            prepared[name] = Path(tmp) / f"upstream-{name}"
            log(f"bench train: {name} ({co}): the stages before train")
            _run_in(co, scene, prepared[name], configs[name], "align")
        for r in range(repeats):
            for name, co in checkouts.items():  # alternately, so both see the same load
                run_dir = Path(tmp) / f"run-{name}-{r}"
                shutil.copytree(prepared[name], run_dir)
                log(f"bench train: {name}, repeat {r + 1}/{repeats}: train + evaluate, train.preset={preset}, "
                    f"device={device}" + (f", {iterations} iterations" if iterations else ""))
                s = _summary(_run_in(co, scene, run_dir, configs[name], None))
                log(f"  {s['iterations_per_s']:.3f} it/s, held-out PSNR {fmt(s['heldout_psnr'], '.2f')} dB, "
                    f"{s['num_gaussians']:,} Gaussians")
                runs[name].append(s)
                shutil.rmtree(run_dir, ignore_errors=True)
    result = {
        "scene": str(scene), "preset": preset, "device": device, "height": height, "iterations": iterations,
        "gpu": torch.cuda.get_device_name() if device == "cuda" else None, "repeats": repeats,
        "checkouts": {k: str(v) for k, v in checkouts.items()}, "this_overrides": this_overrides or {},
        "runs": runs, **_median(runs["this"]),
    }
    if against is not None:
        this, other = _median(runs["this"]), _median(runs["other"])
        result["other"] = other
        result["speedup"] = this["iterations_per_s"] / other["iterations_per_s"]
        if this["heldout_psnr"] is not None and other["heldout_psnr"] is not None:
            result["psnr_delta_db"] = this["heldout_psnr"] - other["heldout_psnr"]
    atomic_write_text(out_json, json.dumps(result, indent=2))
    atomic_write_text(out_md, _markdown(result, scene, against))
    log(_markdown(result, scene, against))
    return result


def _median(rows: list[dict]) -> dict:
    """The per-field median of repeated runs (the step parts too)."""
    def med(k):
        vals = [r[k] for r in rows if r.get(k) is not None]
        return statistics.median(vals) if vals else None

    out = {k: med(k) for k in ("train_seconds", "iterations_per_s", "heldout_psnr", "render_fps", "run_wall_s",
                               "num_gaussians")}
    out["iterations"] = rows[0]["iterations"]
    out["backend"] = rows[0]["backend"]
    out["windows"] = rows[0].get("windows")  # the first repeat's (medians of spans would mix runs)
    out["kernel_variants"] = rows[0].get("kernel_variants")
    parts = [r["step_seconds"] for r in rows if r.get("step_seconds")]
    out["step_seconds"] = {k: statistics.median(p.get(k, 0.0) for p in parts) for k in parts[0]} if parts else None
    return out


def _markdown(r: dict, scene: Path, against: Path | None) -> str:
    where = r["gpu"] or "CPU"
    cmd = f"pano-pipe bench train --device {r['device']} --preset {r['preset']} --height {r['height']}"
    if r["iterations"]:
        cmd += f" --iterations {r['iterations']}"
    if against is not None:
        cmd += f" --against {against} --repeats {r['repeats']}"
    for stage, params in r.get("this_overrides", {}).items():
        cmd += "".join(f" --set {stage}.{k}={v}" for k, v in params.items())
    what = "the simulated demo scene" if "demo" in str(scene) else str(scene)
    rows = [("this", r)] + ([("other", r["other"])] if against is not None else [])
    text = f"""# Training benchmark ({where})

Generated by `{cmd}`: the whole pipeline on {what} at {2 * r['height']}x{r['height']}
(median of {r['repeats']} run(s){', alternating between the checkouts' if against is not None else ''}).

| checkout | iterations | train s | it/s | Gaussians | held-out PSNR dB | render FPS |
|---|---|---|---|---|---|---|
"""
    for name, s in rows:
        label = name if against is None else f"{name} (`{r['checkouts'][name]}`)"
        text += (f"| {label} | {s['iterations']} | {fmt(s['train_seconds'], '.1f')} | "
                 f"{fmt(s['iterations_per_s'], '.3f')} | {int(s['num_gaussians'] or 0):,} | "
                 f"{fmt(s['heldout_psnr'], '.2f')} | {fmt(s['render_fps'], '.0f')} |\n")
    for name, s in rows:
        runs = r.get("runs", {}).get(name, [])
        if len(runs) > 1:  # the first run of a machine also compiles the kernels (Triton's disk cache keeps them)
            text += (f"\nRuns of {name} in order: " + ", ".join(f"{x['iterations_per_s']:.1f}" for x in runs)
                     + " it/s (the first compiles the GPU kernels the later ones find in Triton's cache).\n")
    if against is not None:
        text += (f"\nthis / other: **{r['speedup']:.2f}x** the iterations per second"
                 + (f", held-out PSNR {r['psnr_delta_db']:+.2f} dB" if r.get("psnr_delta_db") is not None else "")
                 + ".\n")
    parts = [(name, s["step_seconds"]) for name, s in rows if s.get("step_seconds")]
    if parts:
        keys = list(dict.fromkeys(k for _, p in parts for k in p))
        text += "\nSeconds per part of the step, summed over the iterations:\n\n"
        text += "| checkout | " + " | ".join(keys) + " |\n|---|" + "---|" * len(keys) + "\n"
        for name, p in parts:
            text += f"| {name} | " + " | ".join(fmt(p.get(k), ".2f") for k in keys) + " |\n"
    for name, s in rows:
        if s.get("windows"):
            text += (f"\nIterations per second through the run ({name}; from train_log.jsonl):\n\n"
                     "| iterations | it/s | Gaussians at the end |\n|---|---|---|\n")
            text += "".join(f"| {w['from']}–{w['to']} | {w['iterations_per_s']:.1f} | {w['gaussians']:,} |\n"
                            for w in s["windows"])
        if s.get("kernel_variants"):
            text += (f"\nTriton kernels' compiled variants in the run ({name}; each a compile, or a load from "
                     "Triton's disk cache): " + ", ".join(f"`{k}` {v}" for k, v in sorted(s["kernel_variants"].items()))
                     + "\n")
    return text
