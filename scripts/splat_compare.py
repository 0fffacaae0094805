"""Splatting forward and forward+backward at one size, this checkout against another one,
in the same run (absolute times on a shared machine vary; their ratio much less).

    python scripts/splat_compare.py --base /tmp/base              # wall clock, alternating
    python scripts/splat_compare.py --base /tmp/base --threads 1  # + CPU time of one thread

Each checkout is timed in its own subprocess (its own compiled kernel), alternately, and the
median of each is reported with the ratio. The CPU time of the calling thread is reported
too: with one thread it is the kernel's own work, which a loaded machine changes far less
than the wall clock (valgrind's instruction counts were the plan, but valgrind cannot decode
the AVX-512 that `-march=native` emits here).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

WORKER = r"""
import json, sys, time, torch
from splatting.bench import indoor_scene
from splatting import EquirectCamera, render
H, W, n, reps, threads = (int(a) for a in sys.argv[1:6])
if threads: torch.set_num_threads(threads)
means, quats, scales, opac, colors = indoor_scene(n)
cam = EquirectCamera(H, W)
vm = torch.eye(4)
params = [t.clone().requires_grad_(True) for t in (means, quats, scales, opac, colors)]
def fwd():
    with torch.no_grad():
        render(*params, vm, cam, backend="cpp")
def fwdbwd():
    out = render(*params, vm, cam, backend="cpp")
    (out.image.sum() + out.depth.mean()).backward()
    for p in params: p.grad = None
fwdbwd()
res = {"fwd": [], "fwdbwd": [], "fwd_cpu": [], "fwdbwd_cpu": []}
for _ in range(reps):
    for k, f in (("fwd", fwd), ("fwdbwd", fwdbwd)):
        c0 = time.thread_time(); t0 = time.perf_counter(); f()
        res[k].append(time.perf_counter() - t0); res[k + "_cpu"].append(time.thread_time() - c0)
print("RESULT" + json.dumps(res))
"""


def _run(checkout: Path, args, reps: int) -> dict:
    env = dict(os.environ, PYTHONPATH=str(checkout))
    if args.threads:
        env["OMP_NUM_THREADS"] = str(args.threads)
    cmd = [sys.executable, "-c", WORKER, str(args.height), str(2 * args.height), str(args.gaussians), str(reps),
           str(args.threads)]
    out = subprocess.run(cmd, env=env, cwd=checkout, capture_output=True, text=True, check=True).stdout
    return json.loads(out.split("RESULT")[1])


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--base", type=Path, required=True, help="the other checkout (e.g. a git worktree)")
    ap.add_argument("--height", type=int, default=512)
    ap.add_argument("--gaussians", type=int, default=100_000)
    ap.add_argument("--rounds", type=int, default=5, help="alternating rounds (wall clock)")
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0 = torch's default)")
    args = ap.parse_args(argv)
    here = Path(__file__).resolve().parents[1]
    checkouts = {"this": here, "base": args.base.resolve()}
    parts = ("fwd", "fwdbwd", "fwd_cpu", "fwdbwd_cpu")
    times = {k: {p: [] for p in parts} for k in checkouts}
    for _ in range(args.rounds):
        for k, c in checkouts.items():
            res = _run(c, args, 3)
            for part in parts:
                times[k][part] += res[part]
    print(f"{args.height}x{2 * args.height}, {args.gaussians:,} Gaussians, {args.rounds} alternating rounds of 3")
    for part in parts:
        a, b = statistics.median(times["this"][part]), statistics.median(times["base"][part])
        print(f"{part:7s} this {a:.4f} s  base {b:.4f} s  base/this {b / a:.2f}x")


if __name__ == "__main__":
    main()
