"""CLI commands `pano-pipe report / ablate / sweep / render` (typer-compatible functions;
pipeline/cli.py registers them). Run folders default to runs/<scene-name>/ exactly as
`pano-pipe run` does (pipeline.settings.make_engine)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from rich.markup import escape

from runtime.console import console
from pipeline.options import ConfigOpt, OutOpt, SceneArg, SetOpt
from runfs.errors import PanoError
from runfs.paths import run_path


def _engine(scene: Path, out: Path | None, config: Path | None = None, set_: list[str] | None = None):
    from pipeline.settings import make_engine

    return make_engine(scene, out, config, set_)


def _print_mean(mean: dict[str, float | None], split: str) -> None:
    """The mean metrics, named by the views they were measured on (training views where the scene
    holds out none: a fit, not generalisation)."""
    from evaluation.report_text import fmt

    shown = ", ".join(f"{k} {fmt(v)}" for k, v in mean.items())
    console.print(f"[bold]{split} metrics:[/] {shown}")


def report_command(scene: SceneArg, out: OutOpt = None, config: ConfigOpt = None, set_: SetOpt = None) -> None:
    """Write the HTML report (self-contained) and its Markdown twin for a run folder.

    --config/--set only matter for the "now" column (is each stage current under that configuration)."""
    from evaluation.report import build_report
    from pipeline.engine import read_output

    engine = _engine(scene, out, config, set_)
    run_dir = engine.out_dir
    if not run_dir.is_dir():
        raise PanoError(run_dir, f"no run folder; run `pano-pipe run all {scene}` first")
    try:
        states = {name: p.state for name, p in engine.plan().items()}
    except PanoError:
        states = None  # a broken config must not stop a report of what exists
    paths = build_report(run_dir, engine.completed_scene(), states=states)
    ev = read_output(run_dir, "evaluate")
    if ev is not None:
        _print_mean(ev.mean, ev.split)
    console.print(f"[bold]report:[/] {escape(str(paths.html))}")
    console.print(f"[bold]markdown:[/] {escape(str(paths.markdown))}")


def ablate_command(
    scene: SceneArg,
    seeds: Annotated[
        Optional[int], typer.Option("--seeds", min=1, help="Seeds per variant (mean ± std); default 1, 3 with --paper.")
    ] = None,
    out: OutOpt = None,
    iterations: Annotated[
        Optional[int], typer.Option("--iterations", min=1, help="Training iterations per variant (default: the train stage's).")
    ] = None,
    paper: Annotated[
        bool, typer.Option("--paper", help="The paper's setting: train preset 'paper' (512x1024, 7k iterations), "
                                           "evaluation at 512x1024, 3 seeds; --set/--config still override.")
    ] = False,
    baseline: Annotated[
        str, typer.Option("--baseline", help="Projection of the 3D-GS* steps: crops (the paper's eight 120° crops) "
                                             "or cubemap.")
    ] = "crops",
    equal: Annotated[
        str, typer.Option("--equal", help="Also compare the projections at an equal budget: time (training seconds), "
                                          "pixels (training pixels rendered) or none (equal iterations only).")
    ] = "time",
    config: ConfigOpt = None,
    set_: SetOpt = None,
) -> None:
    """The paper's ablation: 3D-GS* (random init, perspective crops) / + layout init / + 360° splatting / + layout regularisation."""
    import shlex
    import sys

    from evaluation.ablate_estimate import ablation_estimate
    from evaluation.experiments import PAPER_SEEDS, ablation_variants, paper_config, run_ablation

    engine = _engine(scene, out, config, set_)
    cfg = paper_config(engine.config) if paper else engine.config
    seeds = seeds if seeds is not None else PAPER_SEEDS if paper else 1
    train = engine.registry["train"].params.model_validate(cfg.get("train", {}))
    trainings = seeds * (len(ablation_variants(baseline)) + (equal != "none"))  # + the equal-budget row
    console.print(escape(ablation_estimate(engine.out_dir, trainings, iterations or int(train.resolved("iterations")),
                                           int(train.resolved("height")))), soft_wrap=True)
    command = "pano-pipe " + " ".join(shlex.quote(a) for a in sys.argv[1:]) if sys.argv[1:2] == ["ablate"] else None
    res = run_ablation(engine.scene, engine.out_dir, cfg, seeds=seeds, iterations=iterations,
                       log=console.print, baseline=baseline, command=command, equal=equal)
    console.print(res["table"])
    if res.get("projection_table"):
        console.print(res["projection_table"])
    for n in res["notes"]:
        console.print(n)
    console.print("[bold]ablation:[/] " + escape(f"{res['markdown']} · {res['json']} · {res['chart']}"))


def sweep_command(
    scene: SceneArg,
    out: OutOpt = None,
    iterations: Annotated[str, typer.Option("--iterations", help="Comma-separated iteration counts.")] = "300,1000",
    heights: Annotated[str, typer.Option("--heights", help="Comma-separated training heights (width = 2×height).")] = "64,128",
    caps: Annotated[str, typer.Option("--caps", help="Comma-separated Gaussian caps; 'default' = the train preset's cap.")] = "5000,default",
    eval_height: Annotated[
        Optional[int], typer.Option("--eval-height", min=8, help="Evaluation height for every point (default: the largest training height).")
    ] = None,
    config: ConfigOpt = None,
    set_: SetOpt = None,
) -> None:
    """Accuracy against cost: iterations × training resolution × Gaussian cap → PSNR vs training seconds and FPS."""
    from evaluation.experiments import parse_grid, run_sweep

    engine = _engine(scene, out, config, set_)
    res = run_sweep(engine.scene, engine.out_dir, engine.config, parse_grid(iterations), parse_grid(heights),
                    parse_grid(caps, allow_none=True), eval_height=eval_height, log=console.print)
    console.print(res["table"])
    console.print("[bold]sweep:[/] " + escape(f"{res['markdown']} · {res['json']} · {res['chart']}"))


def render_command(
    scene: SceneArg,
    path: Annotated[
        str,
        typer.Option("--path", help="Views to fly through: train, test, all, comma-separated view names, "
                                    "or a nerfstudio camera_path.json file."),
    ] = "train",
    perspective: Annotated[bool, typer.Option("--perspective", help="A 90° pinhole view instead of the panorama.")] = False,
    frames: Annotated[
        Optional[int], typer.Option("--frames", min=1, help="Number of frames (default 60; a camera path file sets its own).")
    ] = None,
    out: OutOpt = None,
    height: Annotated[
        Optional[int], typer.Option("--height", min=8, help="Frame height (default: the training height, or the path file's).")
    ] = None,
    fps: Annotated[
        Optional[float], typer.Option("--fps", min=1, help="Video frame rate (default 24, or the path file's).")
    ] = None,
    world_up: Annotated[
        str, typer.Option("--world-up", help="Up axis of a camera path file's nerfstudio world: +z, +y or -y "
                                             "(as for import-nerfstudio).")
    ] = "+z",
    overwrite: Annotated[
        bool, typer.Option("--overwrite", help="Replace an existing video of the same name (default: write NAME-2.mp4, ...).")
    ] = False,
    backend: Annotated[Optional[str], typer.Option("--backend", help="Splatting backend (default: the renderer's).")] = None,
) -> None:
    """A fly-through video (H.264 mp4) along the views or a camera path file, rendered from the trained model."""
    import math

    from evaluation.flythrough import (
        even_size,
        is_path_file,
        output_path,
        path_views,
        read_camera_path,
        render_flythrough,
        walk_poses,
    )
    from evaluation.model_io import equirect_camera, load_model, pinhole_camera, recorded_background
    from runtime.console import track
    from pipeline.engine import load_artifact
    from schemas.train import TrainOutput

    engine = _engine(scene, out)
    tdir = engine.out_dir / "train"
    if not (tdir / "artifact.json").is_file():
        raise PanoError(tdir / "artifact.json", f"missing; train first with `pano-pipe run train {scene}`")
    train = load_artifact(tdir, TrainOutput)
    train_h = int(train.data.resolution[0])
    if is_path_file(path):
        cp = read_camera_path(Path(path), world_up=world_up)
        if frames is not None and frames != len(cp.poses):
            console.print(f"[yellow]note:[/] --frames ignored: {escape(path)} sets {len(cp.poses)} frames")
        poses = cp.poses
        persp = perspective or cp.kind == "perspective"
        fps = fps or cp.fps or 24.0
        if persp:
            h = height or cp.height or train_h
            if cp.height and cp.width:
                w = round(h * cp.width / cp.height)
            else:
                w = round(h * (cp.aspect or 4 / 3))
            h, w = even_size(h, w)
            # nerfstudio's fov is vertical; ours is horizontal
            fov_h = math.degrees(2 * math.atan(math.tan(math.radians(cp.fov_deg) / 2) * w / h))
            camera = pinhole_camera(h, w, fov_deg=min(fov_h, 179.0))
        else:
            h = height or cp.height or train_h
            h, w = even_size(h, 2 * h)
            camera = equirect_camera(h, w)
    else:
        views = path_views(engine.completed_scene(), path)
        poses = walk_poses([v.pose_matrix for v in views], frames or 60)
        persp = perspective
        fps = fps or 24.0
        h = int(height or train_h)
        h, w = even_size(h, 2 * int(round(h * 2 / 3)) if persp else 2 * h)
        camera = pinhole_camera(h, w) if persp else equirect_camera(h, w)
    from runfs.limits import pixels_problem

    if problem := pixels_problem(h, w):  # before a frame of that size is allocated
        raise PanoError("--height" if height else path, f"a frame {problem} (raise --max-megapixels if you mean it)")
    g = load_model(train.path(train.data.ply))
    target = output_path(run_path(engine.out_dir, "render"), path, "persp" if persp else "pano", overwrite=overwrite)
    res = render_flythrough(g, poses, camera, target, fps=fps, backend=backend, track=track,
                            background=recorded_background(train.data.settings, train.meta.params))
    console.print(f"[bold]video:[/] {escape(str(res.path))} ({res.frames} frames, {res.size[0]}×{res.size[1]} (H×W), "
                  f"H.264, {fps:g} fps, {res.frames / max(res.seconds, 1e-9):.1f} frames/s rendered)")
