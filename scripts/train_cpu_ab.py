"""CPU seconds of one training step, one thread, this checkout against another, each through its
own `train` stage (its own code, kernel and defaults), alternating run by run:

    python scripts/train_cpu_ab.py SCENE OTHER_CHECKOUT [--iterations 40] [--repeats 2] [--set k=v ...]
    python scripts/train_cpu_ab.py SCENE . --set-other train.random_turns=false   # one setting's cost

CPU time of a single-threaded process hardly moves when other jobs share the machine, where
`pano-pipe bench train --against` (wall clock, two threads) does: under a load of 10 on two
cores, its it/s varied 2x between repeats of the same code. A step's cost is the CPU time of an
N-iteration run minus a 2-iteration one, over N - 2 (image loading, initialisation and the PLY
export cancel). The stages before `train` run once per checkout, in `<work>/up_<name>`.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

# Runs in the checkout (PYTHONPATH): the upstream stages once, then `train` on a copy, timed.
_WORKER = r"""
import json, shutil, sys, time
from pathlib import Path
import torch
torch.set_num_threads(1)
from pipeline.engine import Engine
from pipeline.registry import build_registry
try:
    from schemas.scene_loader import load_scene
except ImportError:  # older checkouts
    from pipeline.scene_loader import load_scene
scene, upstream, run_dir, config = Path(sys.argv[1]), Path(sys.argv[2]), Path(sys.argv[3]), json.loads(sys.argv[4])
if not upstream.exists():
    Engine(load_scene(scene), upstream, build_registry(), config).run(until="align")
shutil.rmtree(run_dir, ignore_errors=True)
shutil.copytree(upstream, run_dir, ignore=shutil.ignore_patterns("train", "evaluate"))
t0 = time.process_time()
Engine(load_scene(scene), run_dir, build_registry(), config).run(until="train")
print("AB-RESULT " + json.dumps({"cpu": time.process_time() - t0}))
"""


def _run(checkout: Path, scene: Path, work: Path, name: str, config: dict) -> float:
    env = dict(os.environ, PYTHONPATH=str(checkout), OMP_NUM_THREADS="1")
    proc = subprocess.run([sys.executable, "-c", _WORKER, str(scene), str(work / f"up_{name}"), str(work / f"run_{name}"),
                           json.dumps(config)], cwd=checkout, env=env, capture_output=True, text=True)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("AB-RESULT ")]
    if not lines:
        sys.exit(f"{checkout}: the run failed\n{proc.stderr[-3000:]}")
    return json.loads(lines[0].split(" ", 1)[1])["cpu"]


def _settings(items: list[str], preset: str) -> dict:
    """{"preset": ..., PARAM: value} from train.PARAM=VALUE items (values as JSON where they parse)."""
    out = {"preset": preset}
    for item in items:
        key, value = item.split("=", 1)
        try:
            out[key.removeprefix("train.")] = json.loads(value)
        except ValueError:
            out[key.removeprefix("train.")] = value
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene", type=Path)
    ap.add_argument("other", type=Path, help="another pano-pipe checkout (e.g. a git worktree of an older commit)")
    ap.add_argument("--iterations", type=int, default=40)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--preset", default="paper")
    ap.add_argument("--set", action="append", default=[], help="train.PARAM=VALUE for this checkout")
    ap.add_argument("--set-other", action="append", default=[], help="train.PARAM=VALUE for the other")
    a = ap.parse_args()
    settings = {"this": _settings(a.set, a.preset), "other": _settings(a.set_other, a.preset)}
    checkouts = {"this": Path(__file__).resolve().parents[1], "other": a.other.resolve()}
    work = Path(tempfile.mkdtemp(prefix="train-cpu-ab-"))
    config = lambda name, its: {"train": {**settings[name], "iterations": its}}  # noqa: E731
    for name, co in checkouts.items():  # the upstream stages and the kernel build, untimed
        _run(co, a.scene, work, name, config(name, 2))
    runs = {n: {"short": [], "long": []} for n in checkouts}
    for r in range(a.repeats):
        for name, co in checkouts.items():
            runs[name]["short"].append(_run(co, a.scene, work, name, config(name, 2)))
            runs[name]["long"].append(_run(co, a.scene, work, name, config(name, a.iterations)))
            print(f"{name} repeat {r + 1}: {runs[name]['short'][-1]:.1f} s (2 iterations), "
                  f"{runs[name]['long'][-1]:.1f} s ({a.iterations})", flush=True)
    step = {n: (statistics.median(v["long"]) - statistics.median(v["short"])) / (a.iterations - 2)
            for n, v in runs.items()}
    print(f"CPU seconds per step, one thread: this {step['this']:.3f}, other {step['other']:.3f}; "
          f"other / this = {step['other'] / step['this']:.2f}x")
    shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
