"""`pano-pipe bench poses`: the poses stage's methods on simulated scenes without poses, against
the simulator's true poses (docs/poses.md).

The scenes have the hard parts of real captures: the `suite` preset (three rooms joined by
openings, a third of the walls bare), one tripod height, the capture effects (noise, exposure,
tripod, with the nadir masked as for a real capture), neighbours 1-6 m apart; `chain` puts the
cameras along a walk through the rooms, each seeing its neighbours on the walk most.
"""

from __future__ import annotations

import json
import os
import platform
import shutil
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from rich.markup import escape

from runtime.console import console
from runfs.fsutil import atomic_write_text
from sfm.frame import nearest_rotation, rotation_angle_deg

#: Simulator effects of a bench scene: textured, furnished, shaded, the fine detail SfM needs, and
#: the capture effects (sensor noise, exposure, a tripod at the nadir).
SCENE_EFFECTS = "texture,furniture,shading,aa,detail,noise,exposure,tripod"
#: The tripod of every simulated capture: one height, as real captures are taken.
TRIPOD_HEIGHT = 1.5
#: The nadir cap a real capture masks (the tripod travels with the camera).
NADIR_MASK_DEG = 35.0
METHODS = ("auto", "equirect", "rig", "upright")


@dataclass(frozen=True)
class BenchScene:
    label: str
    views: int
    walk: bool = False
    #: the simulator's `plain-floor` effect: a floor structure from motion finds (almost) no point on
    plain_floor: bool = False

    @staticmethod
    def parse(text: str) -> BenchScene:
        """'8' (8 views spread over the rooms), 'chain8' (8 views along a walk), 'plain13' or
        'plainchain8' (the same with a plain floor: no texture, no detail)."""
        plain = text.startswith("plain")
        rest = text.removeprefix("plain")
        walk = rest.startswith("chain")
        count = rest.removeprefix("chain")
        if not count.isdigit() or not 2 <= int(count) <= 64:
            raise ValueError(f"scene {text!r}: a view count 2..64, chainN, plainN or plainchainN")
        return BenchScene(text, int(count), walk, plain)


def simulate_capture(out: Path, views: int, height: int, seed: int = 0, walk: bool = False,
                     plain_floor: bool = False) -> dict[str, np.ndarray]:
    """Write an unposed simulated capture (suite preset) at `out`; return the true camera-to-world poses.
    `plain_floor`: the floor without texture or detail (the simulator's `plain-floor` effect)."""
    import simulate

    with tempfile.TemporaryDirectory(prefix="pano-sim-") as tmp:
        sim = Path(tmp) / "sim"
        simulate.generate_scene(sim, preset="suite", views=views, test_views=0, height=height, seed=seed,
                                effects=SCENE_EFFECTS + (",plain-floor" if plain_floor else ""), walk=walk,
                                tripod_height=TRIPOD_HEIGHT)
        truth = unposed_copy(sim, out)
    manifest = json.loads((out / "scene.json").read_text())
    manifest["nadir_mask_deg"] = NADIR_MASK_DEG
    (out / "scene.json").write_text(json.dumps(manifest, indent=1))
    return truth


def unposed_copy(scene_dir: Path, out: Path) -> dict[str, np.ndarray]:
    """Write a scene at `out` with the images of `scene_dir` and a manifest that lists only names,
    images, splits and camera heights; return the true camera-to-world poses."""
    manifest = json.loads((scene_dir / "scene.json").read_text())
    truth = {v["name"]: np.asarray(v["pose"]) for v in manifest["views"]}
    manifest["views"] = [{k: v[k] for k in ("name", "image", "split", "camera_height") if k in v}
                         for v in manifest["views"]]
    for v in manifest["views"]:
        (out / v["image"]).parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(scene_dir / v["image"], out / v["image"])
    manifest.pop("floor_plan", None)
    (out / "scene.json").write_text(json.dumps(manifest, indent=1))
    return truth


def similarity_errors(recovered: dict[str, np.ndarray], truth: dict[str, np.ndarray]
                      ) -> tuple[dict[str, tuple[float, float]], float]:
    """Per view (position error in metres, rotation error in degrees) of camera-to-world poses after
    the similarity (rotation, translation, scale) that best aligns `recovered` to `truth`, and that
    scale (1 when the recovered metric scale is right)."""
    names = [v for v in recovered if v in truth]
    rotation = nearest_rotation(sum(truth[v][:3, :3] @ recovered[v][:3, :3].T for v in names))
    src = np.array([rotation @ recovered[v][:3, 3] for v in names])
    dst = np.array([truth[v][:3, 3] for v in names])
    src_c, dst_c = src - src.mean(axis=0), dst - dst.mean(axis=0)
    scale = float(np.sum(src_c * dst_c) / np.sum(src_c * src_c)) if np.sum(src_c * src_c) > 0 else 1.0
    return {v: (float(np.linalg.norm(scale * s - d)),
                rotation_angle_deg((rotation @ recovered[v][:3, :3]).T @ truth[v][:3, :3]))
            for v, s, d in zip(names, src_c, dst_c)}, scale


def bench_poses(scenes: list[BenchScene], methods: list[str], height: int, seed: int, threads: int | None,
                out_md: Path, out_json: Path) -> dict:
    from pipeline.engine import Engine, read_output
    from pipeline.registry import build_registry
    from schemas.scene_loader import load_scene

    rows = []
    with tempfile.TemporaryDirectory(prefix="pano-bench-poses-") as tmp:
        for bench in scenes:
            scene_dir = Path(tmp) / f"scene-{bench.label}"
            truth = simulate_capture(scene_dir, bench.views, height, seed, bench.walk, bench.plain_floor)
            for method in methods:
                config = {"poses": {"method": method, "working_height": height, "threads": threads}}
                run_dir = Path(tmp) / f"run-{bench.label}-{method}"
                t0, cpu0 = time.perf_counter(), time.process_time()
                try:
                    Engine(load_scene(scene_dir), run_dir, build_registry(), config).run(target="poses")
                    failure = None
                except Exception as e:  # a method that fails is a result of the bench, not its end
                    failure = " ".join(str(e).split())
                seconds = time.perf_counter() - t0
                # CPU seconds of this process (every thread): on a shared machine the wall clock
                # measures the neighbours too; CPU time / cores bounds what an idle machine takes
                cpu = time.process_time() - cpu0
                row = {"scene": bench.label, "views": bench.views, "method": method, "seconds": seconds,
                       "cpu_seconds": cpu, "failure": failure}
                if failure is None:
                    data = read_output(run_dir, "poses")
                    posed = {v.view: np.asarray(v.pose) for v in data.views if v.registered}
                    errors, scale = similarity_errors(posed, truth)
                    row.update(
                        used=data.method, registered=len(posed), points=data.points,
                        residual_deg=data.residual_deg,
                        max_position_cm=100 * max(e[0] for e in errors.values()),
                        max_rotation_deg=max(e[1] for e in errors.values()),
                        scale_error_pct=100 * abs(1.0 / scale - 1.0), timings_s=data.timings_s)
                rows.append(row)
                console.print(escape(f"{bench.label}, {method}: " + (failure or (
                    f"{row['registered']}/{bench.views} placed by {row['used']}, {row['max_position_cm']:.2f} cm, "
                    f"{row['max_rotation_deg']:.3f}°, scale off {row['scale_error_pct']:.2f} %, "
                    f"{seconds:.1f} s ({cpu:.1f} CPU s)"))), soft_wrap=True)
    result = {"machine": f"{platform.platform()}, {os.cpu_count()} CPUs", "height": height, "seed": seed,
              "threads": threads, "rows": rows}
    atomic_write_text(out_json, json.dumps(result, indent=2))
    def cells(r: dict) -> str:
        if r["failure"]:
            return f"failed: {r['failure']} | | | | | | {r['seconds']:.1f} | {r['cpu_seconds']:.1f}"
        return (f"{r['used']} | {r['registered']}/{r['views']} | {r['points']} | {r['max_position_cm']:.2f} | "
                f"{r['max_rotation_deg']:.3f} | {r['scale_error_pct']:.2f} | {r['seconds']:.1f} | "
                f"{r['cpu_seconds']:.1f}")

    table = "\n".join(f"| {r['scene']} | {r['method']} | {cells(r)} |" for r in rows)
    atomic_write_text(out_md, f"""# Poses benchmark

Generated by `pano-pipe bench poses` on {result['machine']}: simulated captures (preset suite:
three rooms joined by openings; {SCENE_EFFECTS}; one tripod height {TRIPOD_HEIGHT} m; nadir
masked {NADIR_MASK_DEG:g}°), {2 * height}x{height} panoramas, seed {seed}, no poses given; `chainN`:
cameras along a walk. Errors after the best similarity onto the true poses; scale: the stage's
metric scale against the truth.

| scene | method | used | placed | points | max position error (cm) | max rotation error (°) | scale error (%) | seconds | CPU seconds |
|---|---|---|---|---|---|---|---|---|---|
{table}
""")
    console.print(f"wrote {escape(str(out_md))} and {escape(str(out_json))}")
    return result
