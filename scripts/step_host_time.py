"""Host time of one training step on the GPU's code path, measured without a GPU.

A GPU step costs max(host time, device time): the kernels run asynchronously while Python and
torch's dispatcher queue the next ones. This measures the first term anywhere: the trainer runs
the `cuda` backend's step on CPU tensors (splatting.devices.KERNELS_ON_CPU, as the op-count test
does) with every Triton launch replaced by a no-op, on a tiny scene (60 Gaussians, 16×32) and a
pair capacity of 1024, so what torch computes on the CPU is negligible and what is left is the
Python and dispatch a GPU step pays. Between densifications, no logging, one thread.

    TRITON_INTERPRET=1 PYTHONPATH=$PWD python scripts/step_host_time.py [--steps 500] [--profile]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import torch


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=500)
    ap.add_argument("--profile", action="store_true", help="also print cProfile's top functions by own time")
    args = ap.parse_args(argv)
    if os.environ.get("TRITON_INTERPRET") != "1":
        print("set TRITON_INTERPRET=1 (the kernels' launch path on CPU tensors)", file=sys.stderr)
        return 2
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "train"))
    import triton.runtime.interpreter as interpreter
    from train_helpers import load_views, rooms, small_config, tiny_scene

    from gaussians import losses
    from gaussians.init import random_points
    from gaussians.trainer import Trainer, scene_extent
    from splatting import bin_triton, devices

    torch.set_num_threads(1)
    losses._cpu_kernels = lambda x: None  # the fused Triton loss, as on a GPU
    devices.KERNELS_ON_CPU = True
    root = tiny_scene(Path(tempfile.mkdtemp()) / "room")
    g = random_points(60, 0, rooms=rooms(root))
    never = 10**9
    cfg = small_config(iterations=never, extent=scene_extent(g.means), backend="cuda", densify_from=never,
                       densify_until=never, log_every=never, sh_degree_every=0, device="cpu")
    trainer = Trainer(g, load_views(root, height=16), cfg)
    trainer.part_seconds = None
    trainer.step()  # with the real kernels: sizes the pair list
    # from here the kernels do nothing, so the pair counts they would write are garbage: the
    # capacity is fixed (and small: its sorts are device work on a GPU)
    interpreter.InterpretedFunction.__getitem__ = lambda self, grid: (lambda *a, **k: None)
    cap = bin_triton.capacity_for(torch.device("cpu"))
    cap.capacity = 1024
    cap.poll = cap.record = lambda *a: None
    cap.needs_sizing = lambda n: False
    for _ in range(50):
        trainer.step()
    t0 = time.perf_counter()
    for _ in range(args.steps):
        trainer.step()
    per_step = (time.perf_counter() - t0) / args.steps
    print(f"host time per training step (launches stubbed, {args.steps} steps): {per_step * 1e3:.3f} ms "
          f"= at most {1 / per_step:.0f} it/s whatever the GPU")
    if args.profile:
        import cProfile
        import pstats

        prof = cProfile.Profile()
        prof.runcall(lambda: [trainer.step() for _ in range(args.steps)])
        pstats.Stats(prof).sort_stats("tottime").print_stats(25)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
