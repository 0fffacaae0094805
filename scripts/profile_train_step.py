"""Profile training steps of a real run: where a step's time goes, kernel by kernel.

    python scripts/profile_train_step.py SCENE UPSTREAM_RUN --device cuda --out docs/gpu_check

UPSTREAM_RUN is a run folder of SCENE with the stages before train done (`pano-pipe run align
SCENE --out RUN`, or what `bench train` prepares). The train stage runs as `run all` would run
it, for --warmup + --steps iterations; the last --steps are timed (synchronised at both ends,
so the figure is the step's wall time) and then run once more under torch.profiler.
Writes profile_step.txt (per-op table by device time and by host time, launches per step).
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from pathlib import Path

import torch


def launch_costs(device: str, n: int = 2000) -> dict[str, float]:
    """Host microseconds per launch of an empty Triton kernel and of a small torch op (the unit
    a host-bound step is made of), the device kept busy so the host never waits."""
    import triton
    import triton.language as tl

    @triton.jit
    def _noop(x, n, BLOCK: tl.constexpr):
        i = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
        tl.store(x + i, tl.load(x + i, mask=i < n), mask=i < n)

    x = torch.zeros(1024, device=device)
    out = {}
    for name, fn in (("triton_launch_us", lambda: _noop[(1,)](x, 1024, BLOCK=1024)),
                     ("torch_op_us", lambda: x.add_(1.0))):
        fn()
        torch.cuda.synchronize()
        t0 = time.perf_counter()
        for _ in range(n):
            fn()
        out[name] = 1e6 * (time.perf_counter() - t0) / n
        torch.cuda.synchronize()
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", type=Path)
    ap.add_argument("upstream", type=Path)
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--preset", default="paper")
    ap.add_argument("--height", type=int, default=512)
    ap.add_argument("--warmup", type=int, default=300)
    ap.add_argument("--steps", type=int, default=50)
    ap.add_argument("--out", type=Path, default=Path("docs/gpu_check"))
    a = ap.parse_args()

    from gaussians.trainer import Trainer
    from pipeline.engine import Engine
    from pipeline.registry import build_registry
    from schemas.scene_loader import load_scene

    cuda = a.device == "cuda"
    sync = torch.cuda.synchronize if cuda else (lambda: None)
    first, last = a.warmup + 1, a.warmup + a.steps  # timed: iterations first..last
    found: dict = {}
    original = Trainer.step

    def step(self):
        if self.iteration + 1 == first:
            sync()
            found["t0"] = time.perf_counter()
        info = original(self)
        if self.iteration == last:
            sync()
            found["step_ms"] = 1e3 * (time.perf_counter() - found["t0"]) / a.steps
            found["gaussians"] = len(self.g)
            acts = [torch.profiler.ProfilerActivity.CPU] + ([torch.profiler.ProfilerActivity.CUDA] if cuda else [])
            with torch.profiler.profile(activities=acts) as prof:
                for _ in range(a.steps):
                    original(self)
                sync()
            found["prof"] = prof
        return info

    Trainer.step = step
    config = {"train": {"preset": a.preset, "device": a.device, "height": a.height,
                        "iterations": a.warmup + 2 * a.steps, "checkpoint_every": 0},
              "evaluate": {"device": a.device}}
    with tempfile.TemporaryDirectory(prefix="pano-profile-") as tmp:
        run = Path(tmp) / "run"
        shutil.copytree(a.upstream, run)
        Engine(load_scene(a.scene), run, build_registry(), config).run(until="train")
    prof = found["prof"]
    events = prof.key_averages()
    on_device = [e for e in events if getattr(e, "device_type", None) == torch.autograd.DeviceType.CUDA]
    kernels = sum(e.count for e in on_device)
    busy_ms = sum(getattr(e, "self_device_time_total", 0.0) for e in on_device) / 1e3 / a.steps
    costs = launch_costs(a.device) if cuda else {}
    head = (f"{a.steps} training steps after {a.warmup}, train.preset={a.preset}, {2 * a.height}x{a.height}, "
            f"{found['gaussians']:,} Gaussians, {a.device}"
            + (f" ({torch.cuda.get_device_name()})" if cuda else "") + "\n"
            f"step wall time without the profiler: {found['step_ms']:.2f} ms\n"
            f"device kernels per step: {kernels / a.steps:.1f}, the device busy {busy_ms:.2f} ms of it\n"
            + "".join(f"host time per launch, {k[:-3].replace('_', ' ')}: {v:.1f} us\n" for k, v in costs.items()))
    by_device = events.table(sort_by="self_cuda_time_total" if cuda else "self_cpu_time_total", row_limit=40)
    by_host = events.table(sort_by="cpu_time_total", row_limit=25)
    a.out.mkdir(parents=True, exist_ok=True)
    text = head + "\n## by device time\n" + by_device + "\n## by host time (inclusive)\n" + by_host
    (a.out / "profile_step.txt").write_text(text)
    (a.out / "profile_step.json").write_text(json.dumps(
        {"step_ms": found["step_ms"], "kernels_per_step": kernels / a.steps, "device_busy_ms": busy_ms, "gaussians": found["gaussians"], **costs,
         "device": a.device, "preset": a.preset, "height": a.height}, indent=2))
    print(head)


if __name__ == "__main__":
    main()
