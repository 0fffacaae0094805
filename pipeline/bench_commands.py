"""`pano-pipe bench ...`: what accuracy costs in time (each bench lives beside its package; this
module holds their command-line side). pipeline/cli.py mounts `bench_app` as `bench`."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.markup import escape

from runtime.console import console
from pipeline.options import ConfigOpt, SetOpt
from pipeline.settings import load_config
from runfs.errors import PanoError

bench_app = typer.Typer(help="Benchmarks: what accuracy costs in time.", no_args_is_help=True)

#: Benchmarks write their tables here unless told otherwise: never into a checkout's docs/ by
#: accident (`make bench` passes --out docs on purpose).
BENCH_OUT = Path("runs/bench")
BenchOutOpt = Annotated[Path, typer.Option("--out", help="Folder for the bench_<name>.{json,md} results.")]


@bench_app.command("render")
def bench_render(
    quick: Annotated[bool, typer.Option(help="A small grid (128x256 and 512x1024; 20k and 100k).")] = False,
    resolutions: Annotated[str, typer.Option(help="HxW list.")] = "128x256,256x512,512x1024",
    counts: Annotated[str, typer.Option(help="Gaussian counts.")] = "20000,100000,300000",
    backends: Annotated[str, typer.Option(help="cpp,torch")] = "cpp,torch",
    repeats: Annotated[int, typer.Option(help="Timed repeats (median).")] = 3,
    device: Annotated[str, typer.Option(
        help="cpu: the CPU table; cuda: the GPU table (512x1024 and 1024x2048, 100k-1M Gaussians, "
             "cuda vs torch backends; bench_render_gpu.{json,md}).")] = "cpu",
    tile_sizes: Annotated[Optional[str], typer.Option(
        help="With --device cuda: the tile sizes (pixels) of the cuda backend's rows, e.g. 8,16 "
             "(default: the renderer's).")] = None,
    out: BenchOutOpt = BENCH_OUT,
) -> None:
    """Renderer speed, memory, cubemap baseline and tangent-plane accuracy, per backend."""
    if device not in ("cpu", "cuda"):
        raise PanoError("--device", f"must be cpu or cuda, got {device!r}")
    if device == "cuda":
        from splatting import bench_gpu

        reason = bench_gpu.no_cuda_reason()
        if reason:
            raise PanoError("--device", reason)
        tiles = {}
        if tile_sizes is not None:
            try:
                tiles["tile_sizes"] = tuple(int(t) for t in tile_sizes.split(","))
            except ValueError:
                raise PanoError("--tile-sizes", f"must be integers separated by commas, got {tile_sizes!r}") from None
            from splatting.render import MAX_TILE

            if not all(1 <= t <= MAX_TILE for t in tiles["tile_sizes"]):
                raise PanoError("--tile-sizes", f"each must be 1..{MAX_TILE}, got {tile_sizes!r}")
        bench_gpu.run_gpu_render_bench(out_json=out / "bench_render_gpu.json", out_md=out / "bench_render_gpu.md",
                                       **tiles)
        return
    from splatting.bench import main as bench_main

    bench_main(
        [
            "--resolutions", resolutions, "--counts", counts, "--backends", backends,
            "--repeats", str(repeats), "--out-json", str(out / "bench_render.json"),
            "--out-md", str(out / "bench_render.md"),
            *(["--quick"] if quick else []),
        ]
    )


@bench_app.command("kernels")
def bench_kernels_command(
    out: BenchOutOpt = BENCH_OUT,
    doc: Annotated[Optional[Path], typer.Option(
        help="Also replace the table between the kernel-table markers of this file (docs/gpu.md).")] = None,
) -> None:
    """The cuda backend's Triton kernels compiled ahead of time for sm_80 and sm_90 (no GPU needed):
    registers, spills, shared memory, SASS instructions per Gaussian-pixel pair of the inner loops."""
    from splatting import kernel_report

    try:
        rows = kernel_report.report_in_subprocess()
    except (ImportError, RuntimeError) as exc:
        raise PanoError("triton", str(exc).splitlines()[0]) from None
    kernel_report.write(rows, out / "bench_kernels.md", out / "bench_kernels.json", doc)


@bench_app.command("train")
def bench_train_command(
    scene: Annotated[Optional[Path], typer.Argument(help="Scene folder (default: the simulated demo scene).")] = None,
    device: Annotated[str, typer.Option(help="cpu or cuda.")] = "cuda",
    preset: Annotated[str, typer.Option(help="train.preset: fast, paper or quality.")] = "paper",
    height: Annotated[int, typer.Option(help="Panorama height of the simulated scene and of training.")] = 512,
    iterations: Annotated[Optional[int], typer.Option(min=1, help="train.iterations (default: the preset's).")] = None,
    against: Annotated[Optional[Path], typer.Option(
        help="Another pano-pipe checkout (e.g. a git worktree of an older commit) to run the same bench on, "
             "alternately with this one, and compare.")] = None,
    repeats: Annotated[int, typer.Option(min=1, help="Runs per checkout (medians are reported).")] = 1,
    sets: Annotated[Optional[list[str]], typer.Option(
        "--set", help="STAGE.PARAM=VALUE for this checkout only (repeatable): e.g. the defaults of the older "
                      "checkout given to --against, so that both train the same way.")] = None,
    upstream: Annotated[Optional[Path], typer.Option(
        help="A run folder of SCENE with the stages before train done (e.g. on a machine with open3d): "
             "each repeat trains from a copy of it.")] = None,
    out: BenchOutOpt = BENCH_OUT,
) -> None:
    """Iterations/s, seconds per part of the step and held-out PSNR of a training preset through `run all`."""
    from pipeline.bench_train import bench_train

    overrides, _ = load_config(None, sets)

    if device not in ("cpu", "cuda"):
        raise PanoError("--device", f"must be cpu or cuda, got {device!r}")
    if preset not in ("fast", "paper", "quality"):
        raise PanoError("--preset", f"must be fast, paper or quality, got {preset!r}")
    bench_train(scene, device, preset, height, out / "bench_train.md", out / "bench_train.json",
                iterations=iterations, against=against, repeats=repeats, this_overrides=overrides,
                upstream=upstream)


@bench_app.command("pipeline")
def bench_pipeline_command(
    scene: Annotated[Optional[Path], typer.Argument(help="Scene (default: a fresh `demo` scene).")] = None,
    config: ConfigOpt = None,
    set_: SetOpt = None,
    out: BenchOutOpt = BENCH_OUT,
) -> None:
    """Time a full run and a second, cached run of the same scene."""
    from pipeline.benchmarks import bench_pipeline

    cfg, _ = load_config(config, set_)
    bench_pipeline(scene, cfg, out / "bench_pipeline.md", out / "bench_pipeline.json")


@bench_app.command("poses")
def bench_poses_command(
    scenes: Annotated[str, typer.Option(
        help="Comma-separated simulated captures: N (N views over three rooms), chainN (N views along a "
             "walk), plainN / plainchainN (the same with a plain floor).")] = "8,13,chain8",
    methods: Annotated[str, typer.Option(help="Comma-separated poses.method values to compare.")]
    = "auto,equirect,rig,upright",
    height: Annotated[int, typer.Option(min=64, help="Panorama height (width = 2 x height).")] = 512,
    seed: Annotated[int, typer.Option(min=0, help="Simulator seed.")] = 0,
    threads: Annotated[Optional[int], typer.Option(min=1, help="CPU threads (default: all CPUs).")] = None,
    out: BenchOutOpt = BENCH_OUT,
) -> None:
    """Pose simulated captures from their panoramas alone with each method: accuracy and time."""
    from sfm.bench import METHODS, BenchScene, bench_poses

    try:
        parsed = [BenchScene.parse(v.strip()) for v in scenes.split(",") if v.strip()]
    except ValueError as e:
        raise PanoError("--scenes", str(e)) from None
    chosen = [m.strip() for m in methods.split(",") if m.strip()]
    bad = sorted(set(chosen) - set(METHODS))
    if bad or not chosen:
        raise PanoError("--methods", f"choose from {', '.join(METHODS)}, got {methods!r}")
    bench_poses(parsed, chosen, height, seed, threads, out / "bench_poses.md", out / "bench_poses.json")


@bench_app.command("batch")
def bench_batch_command(
    scenes: Annotated[int, typer.Option(min=1, help="Simulated scenes in the batch.")] = 8,
    height: Annotated[int, typer.Option(min=16, help="Panorama height of each scene.")] = 32,
    iterations: Annotated[int, typer.Option(min=1, help="Training iterations per scene.")] = 300,
    executors: Annotated[str, typer.Option(help="Comma-separated executors to time.")] = "local,ray",
    out: BenchOutOpt = BENCH_OUT,
) -> None:
    """Wall time of one batch of small scenes under each executor (local, ray)."""
    from batch.bench import bench_batch

    result = bench_batch(scenes, height, iterations, [e.strip() for e in executors.split(",") if e.strip()],
                         out / "bench_batch.md", out / "bench_batch.json",
                         log=lambda m: console.print(escape(m), soft_wrap=True))
    for r in result["rows"]:
        console.print(f"{r['executor']}: {r['wall_s']:.1f} s ({r['vs_local']:.2f}x local)")
