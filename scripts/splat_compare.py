"""Splatting forward and forward+backward at one size, this checkout against another one,
in the same run (absolute times on a shared machine vary; their ratio much less).

    python scripts/splat_compare.py --base /tmp/base            # wall clock, alternating
    python scripts/splat_compare.py --base /tmp/base --callgrind  # instruction counts (1 thread)

Each checkout is timed in its own subprocess (its own compiled kernel), alternately, and the
median of each is reported with the ratio. `--callgrind` counts the instructions of the
kernel calls (render_forward / render_backward) under valgrind: independent of the load.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
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
res = {"fwd": [], "fwdbwd": []}
for _ in range(reps):
    for k, f in (("fwd", fwd), ("fwdbwd", fwdbwd)):
        t0 = time.perf_counter(); f(); res[k].append(time.perf_counter() - t0)
print("RESULT" + json.dumps(res))
"""


def _run(checkout: Path, args, reps: int, callgrind: bool) -> dict:
    env = dict(os.environ, PYTHONPATH=str(checkout), OMP_NUM_THREADS=str(args.threads or ""))
    if not args.threads:
        env.pop("OMP_NUM_THREADS")
    cmd = [sys.executable, "-c", WORKER, str(args.height), str(2 * args.height), str(args.gaussians), str(reps),
           str(1 if callgrind else args.threads)]
    if not callgrind:
        out = subprocess.run(cmd, env=env, cwd=checkout, capture_output=True, text=True, check=True).stdout
        return json.loads(out.split("RESULT")[1])
    with tempfile.TemporaryDirectory() as tmp:
        cg = Path(tmp) / "cg.out"
        env["OMP_NUM_THREADS"] = "1"
        subprocess.run(["valgrind", "--tool=callgrind", f"--callgrind-out-file={cg}", "--collect-atstart=no",
                        "--toggle-collect=*render_forward*", "--toggle-collect=*render_backward*", *cmd],
                       env=env, cwd=checkout, capture_output=True, text=True, check=True)
        ann = subprocess.run(["callgrind_annotate", str(cg)], capture_output=True, text=True, check=True).stdout
        total = int(re.search(r"([\d,]+) \(100.0%\)\s+PROGRAM TOTALS", ann).group(1).replace(",", ""))
        return {"instructions": total}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--base", type=Path, required=True, help="the other checkout (e.g. a git worktree)")
    ap.add_argument("--height", type=int, default=512)
    ap.add_argument("--gaussians", type=int, default=100_000)
    ap.add_argument("--rounds", type=int, default=5, help="alternating rounds (wall clock)")
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0 = torch's default)")
    ap.add_argument("--callgrind", action="store_true")
    args = ap.parse_args(argv)
    here = Path(__file__).resolve().parents[1]
    checkouts = {"this": here, "base": args.base.resolve()}
    if args.callgrind:
        r = {k: _run(c, args, 1, True)["instructions"] for k, c in checkouts.items()}
        print(f"instructions (1 warm-up fwd+bwd, 1 fwd, 1 fwd+bwd): this {r['this']:,}  base {r['base']:,}  "
              f"base/this {r['base'] / r['this']:.2f}x")
        return
    times = {k: {"fwd": [], "fwdbwd": []} for k in checkouts}
    for _ in range(args.rounds):
        for k, c in checkouts.items():
            res = _run(c, args, 3, False)
            for part in ("fwd", "fwdbwd"):
                times[k][part] += res[part]
    print(f"{args.height}x{2 * args.height}, {args.gaussians:,} Gaussians, {args.rounds} alternating rounds of 3")
    for part in ("fwd", "fwdbwd"):
        a, b = statistics.median(times["this"][part]), statistics.median(times["base"][part])
        print(f"{part:7s} this {a:.4f} s  base {b:.4f} s  base/this {b / a:.2f}x")


if __name__ == "__main__":
    main()
