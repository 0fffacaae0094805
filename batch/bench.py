"""`pano-pipe bench batch`: the same batch of small simulated scenes under each executor.

Every executor starts from empty run folders; its wall time includes starting it (for Ray:
starting a local instance and its workers), since a user pays for that too. The runs must
agree: the same cache key for every stage of every scene.
"""

from __future__ import annotations

import json
import os
import platform
import tempfile
import time
from pathlib import Path

from runfs.fsutil import atomic_write_text


def bench_batch(scenes: int, height: int, iterations: int, executors: list[str], out_md: Path, out_json: Path,
                num_cpus: int | None = None, log=print) -> dict:
    from batch.executors import make_executor
    from batch.scheduler import run_batch
    from pipeline.engine import read_meta
    from simulate.generate import generate_scene

    cpus = num_cpus or os.cpu_count() or 1
    config = {"train": {"iterations": iterations, "height": height // 2}}
    rows, keys = [], {}
    with tempfile.TemporaryDirectory(prefix="pano-bench-batch-") as tmp:
        root = Path(tmp)
        dirs = []
        for i in range(scenes):
            generate_scene(root / "scenes" / f"room{i:02d}", views=3, test_views=1, height=height, seed=i,
                           effects="none", with_layout=True, with_depth=True)
            dirs.append(root / "scenes" / f"room{i:02d}")
        for name in executors:
            log(f"bench batch: {scenes} scenes, executor {name} ...")
            t0 = time.perf_counter()
            executor = make_executor(name, num_cpus=cpus)
            try:
                results = run_batch(dirs, root / f"runs-{name}", config, "bench", executor)
            finally:
                executor.close()
            wall = time.perf_counter() - t0
            failed = [r.error for r in results if r.failed]
            if failed:
                raise RuntimeError(f"bench batch: {name}: {failed[0]}")
            keys[name] = {(r.name, s): meta.key for r in results for s in r.stages
                          if (meta := read_meta(r.out_dir / s)) is not None}
            stage_s = sum(o.duration_s for r in results for o in r.stages.values())
            rows.append({"executor": name, "wall_s": round(wall, 2), "stage_seconds": round(stage_s, 2),
                         "scenes_per_hour": round(3600 * scenes / wall, 1)})
    base = next((r["wall_s"] for r in rows if r["executor"] == "local"), None)
    for r in rows:
        r["vs_local"] = round(r["wall_s"] / base, 3) if base else None
    agree = len({json.dumps(sorted(k.items())) for k in keys.values()}) == 1
    result = {"scenes": scenes, "height": height, "train_iterations": iterations, "cpus": cpus,
              "machine": f"{platform.machine()}, {os.cpu_count()} cores", "rows": rows,
              "identical_cache_keys": agree,
              "command": f"pano-pipe bench batch --scenes {scenes} --height {height} --iterations {iterations}"}
    atomic_write_text(out_json, json.dumps(result, indent=2))
    lines = [
        f"# Batch executors: {scenes} scenes",
        "",
        f"`{result['command']}` on {result['machine']} ({cpus} CPUs given to Ray). Each scene: "
        f"3 training + 1 test panoramas at {height}x{2 * height}, every stage, training "
        f"{iterations} iterations at {height // 2}x{height}. Wall time from an empty run folder, "
        "starting the executor included. Same cache key for every stage under every executor: "
        f"{'yes' if agree else 'NO'}.",
        "",
        "| executor | wall s | sum of stage s | scenes / hour | vs local |",
        "|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(f"| {r['executor']} | {r['wall_s']:.1f} | {r['stage_seconds']:.1f} | "
                     f"{r['scenes_per_hour']:.0f} | {r['vs_local']:.2f}x |")
    atomic_write_text(out_md, "\n".join(lines) + "\n")
    return result
