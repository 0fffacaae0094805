"""`pano-pipe`: the command line (typer).

Every user-facing failure is one line on stderr and exit code 2; `--debug`
shows the traceback instead.
"""

from __future__ import annotations

import os

# OpenMP threads that busy-wait between parallel regions made 2 threads 10x slower
# than 1 on a shared 2-core machine (docs/training.md); must be set before torch loads.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from pipeline import signals  # noqa: E402

# before anything else loads: libraries imported from here on (pycolmap takes SIGTERM, numpy and
# OpenCV start threads) load with SIGINT/SIGTERM held back (pipeline/signals.py)
signals.guard_imports()

import json  # noqa: E402
import sys
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.table import Table
from rich.text import Text

from rich.markup import escape

from runtime.console import console, err_console
from pipeline.bench_commands import bench_app
from pipeline.options import ConfigOpt, OutOpt, SceneArg, SetOpt
from runfs.errors import PanoError, did_you_mean, one_line
from schemas.scene import REAL_CAPTURE_NADIR_DEG

app = typer.Typer(
    name="pano-pipe",
    help="Indoor 360° panoramas to a Gaussian Splatting model (360-GS, layout-guided).",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
app.add_typer(bench_app, name="bench")

_state = {"debug": False}


def _version() -> str:
    """The installed package's version (pyproject.toml's when run from a checkout)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("pano-pipe")
    except PackageNotFoundError:
        import tomllib

        pyproject = Path(__file__).resolve().parents[1] / "pyproject.toml"
        return tomllib.loads(pyproject.read_text())["project"]["version"]


def _print_version(value: bool) -> None:
    if value:
        console.print(f"pano-pipe {_version()}")
        raise typer.Exit()


@app.callback()
def _main(
    debug: Annotated[bool, typer.Option("--debug", help="Show tracebacks.")] = False,
    version: Annotated[bool, typer.Option(
        "--version", is_eager=True, callback=_print_version, help="Print the version and exit.")] = False,
    max_megapixels: Annotated[
        Optional[float],
        typer.Option("--max-megapixels", min=0.001, help="Refuse larger images (default 64; env PANO_PIPE_MAX_MEGAPIXELS)."),
    ] = None,
) -> None:
    _state["debug"] = debug
    if debug:  # main() keeps library warnings off stderr; --debug shows them
        import warnings

        warnings.simplefilter("default")
    if max_megapixels is not None:
        os.environ["PANO_PIPE_MAX_MEGAPIXELS"] = repr(max_megapixels)


# -- helpers ------------------------------------------------------------------
# tests and scripts call cli.load_config and cli.make_engine
from pipeline.settings import SCENE_CONFIG, load_config, make_engine, scene_config  # noqa: E402,F401


def command_flags(out: Path | None, config: Path | None, overrides: list[str] | None) -> str:
    """The flags a printed follow-up command must repeat to see the same run (--out, --config, --set)."""
    import shlex

    parts = []
    if out is not None:
        parts += ["--out", str(out)]
    if config is not None:
        parts += ["--config", str(config)]
    for item in overrides or []:
        parts += ["--set", item]
    return "".join(" " + shlex.quote(p) for p in parts)


def print_status_table(engine) -> None:
    plans = engine.plan()
    table = Table(title=escape(f"{engine.scene.name} → {engine.out_dir}"))
    for col in ("stage", "state", "last duration", "note"):
        table.add_column(col)
    colours = {"up-to-date": "green", "stale": "yellow", "missing": "red", "skipped": "dim"}
    for name in engine.order:
        p = plans[name]
        dur = f"{p.last_duration_s:.2f} s" if p.last_duration_s is not None else "—"
        table.add_row(name, f"[{colours[p.state]}]{p.state}[/]", dur, escape(p.reason))
    console.print(table)
    for line in engine.hints():
        console.print(escape(line), soft_wrap=True)


# -- commands -----------------------------------------------------------------
@app.command()
def run(
    stage: Annotated[str, typer.Argument(help="A stage name, or 'all'.")],
    scenes: Annotated[list[Path], typer.Argument(
        help="Scene folder(s) holding scene.json, or folders of scene folders (a batch).", show_default=False)],
    out: Annotated[Optional[Path], typer.Option(
        "--out", help="Run folder (default: runs/<scene-name>/); for a batch the root of one per scene "
                      "(default: runs/).")] = None,
    config: ConfigOpt = None,
    set_: SetOpt = None,
    force: Annotated[bool, typer.Option(
        "--force", help="Rerun the named stage (with 'all': every stage) even if it is up to date.")] = False,
    force_upstream: Annotated[bool, typer.Option(
        "--force-upstream", help="Rerun every stage the run touches, upstream ones included.")] = False,
    until: Annotated[Optional[str], typer.Option("--until", help="Stop after this stage.")] = None,
    resume: Annotated[bool, typer.Option("--resume", help="Continue training from its last checkpoint.")] = False,
    executor: Annotated[str, typer.Option(
        "--executor", help="Batch executor: local (this process) or ray (each stage of each scene a Ray task).")
    ] = "local",
    address: Annotated[Optional[str], typer.Option(
        "--address", help="Ray cluster address (default: start a local Ray instance).")] = None,
    retries: Annotated[int, typer.Option(
        "--retries", min=0, help="Ray: times a stage whose worker died is retried.")] = 2,
    connect_timeout: Annotated[float, typer.Option(
        "--connect-timeout", min=0.1, help="Ray: seconds to wait for the cluster at --address.")] = 30.0,
) -> None:
    """Run the pipeline (`all`) or one stage (with anything stale upstream; up-to-date stages are
    reported cached, --force reruns them), on one scene or a batch of scenes (exit code 1 when any
    scene failed)."""
    from batch.scenes import expand_scenes, is_batch

    if is_batch(scenes) or executor != "local" or address is not None:
        return _run_batch(stage, expand_scenes(scenes), out, config, set_, force, until, resume, executor,
                          address, retries, force_upstream, connect_timeout)
    scene = scenes[0]
    engine = make_engine(scene, out, config, set_)
    target = None if stage == "all" else stage
    if target is not None and target not in engine.registry:
        raise PanoError(None, f"unknown stage {stage!r}{did_you_mean(stage, ['all', *engine.order])}; "
                              f"choose 'all' or one of {', '.join(engine.order)}")
    check_run_request(engine, target, until)  # a typo fails before the banner, not after it
    console.print(run_header(engine), soft_wrap=True)
    for line in engine.hints():
        console.print(escape(line), soft_wrap=True)
    print_no_priors_warning(engine, engine.select(target, until))
    results = engine.run(target=target, until=until, force=force, resume=resume, force_upstream=force_upstream)
    table = Table(title="run")
    for col in ("stage", "outcome", "seconds", "note"):
        table.add_column(col)
    for r in results:
        table.add_row(r.name, r.outcome, f"{r.duration_s:.2f}" if r.outcome == "ran" else "", escape(r.reason))
    console.print(table)
    print_run_summary(engine, scene, [r.name for r in results if r.outcome in ("ran", "cached")],
                      command_flags(out if out is not None else engine.out_dir, config, set_),
                      ran=[r.name for r in results if r.outcome == "ran"])


def check_run_request(engine, target: str | None, until: str | None) -> None:
    """Every stage name and stage parameter of a run checked up front (PanoError naming the first
    problem), so nothing is printed or started for a request that cannot run."""
    engine.select(target, until)
    for name in engine.order:
        engine.params_for(name)


def run_header(engine) -> str:
    """One line before a run: what is run, on what, where to."""
    from stages.train import resolve_device

    views = engine.scene.views
    n_train = sum(v.split == "train" for v in views)
    train = engine.params_for("train")
    height = train.resolved("height")
    device = resolve_device(train.device, "train.device")
    backend = f" ({train.backend} backend)" if train.backend else ""
    return escape(f"scene {engine.scene.name}: {len(views)} views ({n_train} train, {len(views) - n_train} test); "
                  f"training at {height}x{2 * height}, preset {train.preset}, "
                  f"on {device}{backend}; output {engine.out_dir}")


def print_no_priors_warning(engine, selected: list[str]) -> None:
    """The banner's warning when the run trains without priors (layout and depth both skipped): what
    that costs and the commands that fetch the models (evaluation/diagnosis.py)."""
    from evaluation.diagnosis import no_priors_message, plans_without_priors

    if plans_without_priors(engine.plan(), selected):
        console.print(f"[yellow]warning:[/] {escape(no_priors_message())}", soft_wrap=True)


def print_run_summary(engine, scene_arg: Path, finished: list[str], flags: str = "",
                      ran: list[str] | None = None) -> None:
    """After a run: what the poses stage found (when it ran), the model, its size, per-view test
    metrics and the next steps (report with the flags this run was given, view, export)."""
    import shlex

    from pipeline.engine import read_output

    out = engine.out_dir
    poses = read_output(out, "poses") if "poses" in (ran or []) else None
    if poses is not None:
        from stages.poses import summary as poses_summary

        console.print(escape(poses_summary(poses)), soft_wrap=True)
    train = read_output(out, "train") if "train" in finished else None
    if train is not None:
        psnr = train.final_train_psnr
        console.print(escape(f"model: {out / 'train' / train.ply} ({train.num_gaussians:,} Gaussians, "
                             f"{train.iterations} iterations"
                             + (f", train PSNR {psnr:.2f} dB" if psnr is not None else "") + ")"),
                      soft_wrap=True)
    ev = read_output(out, "evaluate") if "evaluate" in finished else None
    if ev is not None:
        h, w = ev.resolution
        table = Table(title=f"metrics ({ev.split} views, {h}x{w})", title_justify="left")
        cols = [c for c in ("psnr", "ws_psnr", "ssim", "lpips", "depth_abs_rel", "depth_rmse")
                if any(getattr(v, c) is not None for v in ev.views)]
        table.add_column("view")
        for c in cols:
            table.add_column(c, justify="right")
        for v in ev.views:
            table.add_row(escape(v.view), *(_metric(getattr(v, c)) for c in cols))
        table.add_row("[bold]mean[/]", *(_metric(ev.mean.get(c)) for c in cols))
        console.print(table)
        console.print(escape(f"render speed: {ev.fps:.1f} FPS at {h}x{w}"), soft_wrap=True)
    if train is not None:  # a run without priors, a model that overfits: said beside the numbers
        from evaluation.diagnosis import run_notes
        from pipeline.engine import read_artifact

        upstream = read_artifact(out, "train").meta.upstream
        for note in run_notes(train, upstream, ev, engine.completed_scene()):
            console.print(f"[yellow]warning:[/] {escape(note)}", soft_wrap=True)
    if train is not None:
        scene_q, out_q = shlex.quote(str(scene_arg)), shlex.quote(str(out))
        console.print("next steps:")
        for command, what in ((f"pano-pipe report {scene_q}{flags}", "the HTML report: metrics, timings, settings"),
                              (f"pano-pipe view {scene_q} --out {out_q}", "the model in the browser"),
                              (f"pano-pipe export {out_q} --format ply", "for other viewers (also splat, spz, sog, html, mesh)")):
            console.print(escape(f"  {command}    # {what}"), soft_wrap=True)


def _metric(value: float | None) -> str:
    return "—" if value is None else f"{value:.4g}"


def _run_batch(stage: str, scenes: list[Path], out: Path | None, config: Path | None, set_: list[str] | None,
               force: bool, until: str | None, resume: bool, executor_name: str, address: str | None,
               retries: int, force_upstream: bool, connect_timeout: float = 30.0) -> int:
    from batch.executors import make_executor
    from batch.progress import console as batch_console
    from batch.progress import summary_table
    from batch.scheduler import run_batch

    cfg, source = load_config(config, set_)
    target = None if stage == "all" else stage
    executor = make_executor(executor_name, address=address, retries=retries, connect_timeout=connect_timeout)
    try:
        results = run_batch(scenes, out if out is not None else Path("runs"), cfg, source, executor,
                            target=target, until=until, force=force, resume=resume,
                            force_upstream=force_upstream,
                            config_for=lambda scene_root: scene_config(scene_root, config, set_))
    finally:
        executor.close()
    batch_console.print(summary_table([r.row() for r in results]))
    failed = [r for r in results if r.failed]
    for r in failed:  # in full: the table's column may be cut to the terminal's width
        batch_console.print(Text.assemble((f"{r.name}: ", "red"), r.error), soft_wrap=True)
    batch_console.print(f"{len(results) - len(failed)} of {len(results)} scenes succeeded", soft_wrap=True)
    if failed:
        raise typer.Exit(1)
    return 0


def _type_name(annotation) -> str:
    """A parameter's type as a user reads it: int, float | None, '360' | 'cubemap', list[int]."""
    import types
    import typing

    origin = typing.get_origin(annotation)
    if origin is typing.Literal:
        return " | ".join(repr(a) for a in typing.get_args(annotation))
    if origin in (typing.Union, types.UnionType):
        return " | ".join(_type_name(a) for a in typing.get_args(annotation))
    if origin is not None:
        args = ", ".join(_type_name(a) for a in typing.get_args(annotation))
        return f"{getattr(origin, '__name__', str(origin))}[{args}]"
    if annotation is type(None):
        return "None"
    return getattr(annotation, "__name__", str(annotation))


@app.command()
def params(
    stage: Annotated[Optional[str], typer.Argument(help="One stage (default: every stage).", show_default=False)]
    = None,
) -> None:
    """Every stage parameter with its type, default and description (set with --set STAGE.PARAM=VALUE)."""
    from pipeline.registry import build_registry

    registry = build_registry()
    if stage is not None and stage not in registry:
        raise PanoError(None, f"unknown stage {stage!r}{did_you_mean(stage, registry)}; "
                              f"stages are {', '.join(registry)}")
    for name, spec in registry.items():
        if stage is not None and name != stage:
            continue
        rows = [(f"{name}.{field_name}", _type_name(info.annotation),
                 "(required)" if info.is_required() else repr(info.get_default(call_default_factory=True)),
                 info.description or "")
                for field_name, info in spec.params.model_fields.items()]
        if not console.is_terminal:
            # a pipe or a file: one tab-separated line per parameter, never wrapped (grep, cut, awk)
            # (written to the console's file directly: rich would expand the tabs into spaces)
            print(f"# {name}: {spec.description}", file=console.file)
            for row in rows:
                print("\t".join(row), file=console.file)
            continue
        table = Table(title=f"{name}: {escape(spec.description)}", title_justify="left")
        table.add_column("parameter", no_wrap=True)
        for col in ("type", "default", "description"):
            table.add_column(col, overflow="fold")
        for row in rows:
            table.add_row(*map(escape, row))
        console.print(table)


@app.command()
def status(scene: SceneArg, out: OutOpt = None, config: ConfigOpt = None, set_: SetOpt = None) -> None:
    """Each stage's state (up-to-date / stale / missing / skipped and why) and last duration."""
    print_status_table(make_engine(scene, out, config, set_))


@app.command()
def schema(out: Annotated[Path, typer.Argument(help="Folder to write the JSON Schemas into.")]) -> None:
    """Write the JSON Schema of scene.json and of every stage artifact."""
    from pipeline.registry import all_schemas

    out.mkdir(parents=True, exist_ok=True)
    for name, model in all_schemas().items():
        (out / f"{name}.schema.json").write_text(json.dumps(model.model_json_schema(), indent=2))
        console.print(f"wrote {escape(str(out / (name + '.schema.json')))}")


CameraHeightOpt = Annotated[float | None, typer.Option(
    help="Camera height over the floor (m): scales the poses (and depth) so the cameras stand this high "
         "over the floor found in the data (docs/poses.md).")]
ScaleOpt = Annotated[float | None, typer.Option(help="Multiply translations (and depth) by this instead.")]
NadirOpt = Annotated[float, typer.Option(help="nadir_mask_deg written to scene.json (tripod cap; 0: off).")]


@app.command("import-nerfstudio")
def import_nerfstudio_command(
    transforms: Annotated[Path, typer.Argument(help="nerfstudio transforms.json (EQUIRECTANGULAR).")],
    out: Annotated[Path, typer.Argument(help="Scene folder to write.")],
    world_up: Annotated[str, typer.Option(help="Up axis of the nerfstudio world: +z, +y or -y.")] = "+z",
    test_every: Annotated[int, typer.Option(help="Every Nth frame is a test view (0: none).")] = 8,
    camera_height: CameraHeightOpt = None,
    scale: ScaleOpt = None,
    nadir_mask_deg: NadirOpt = REAL_CAPTURE_NADIR_DEG,
) -> None:
    """Make a scene folder from a nerfstudio transforms.json (depth files kept, in metres)."""
    from pipeline.importers import import_nerfstudio

    path = import_nerfstudio(transforms, out, world_up=world_up, test_every=test_every,
                             camera_height=camera_height, scale=scale, nadir_mask_deg=nadir_mask_deg)
    console.print(f"wrote {escape(str(path))}", soft_wrap=True)


@app.command("import-colmap")
def import_colmap_command(
    model_dir: Annotated[Path, typer.Argument(help="COLMAP sparse model folder (cameras/images/points3D .bin or .txt).")],
    images_dir: Annotated[Path, typer.Argument(help="Folder the model's image names are relative to.")],
    out: Annotated[Path, typer.Argument(help="Scene folder to write.")],
    camera_height: CameraHeightOpt = None,
    scale: ScaleOpt = None,
    test_every: Annotated[int, typer.Option(help="Every Nth image (by name) is a test view (0: none).")] = 0,
    nadir_mask_deg: NadirOpt = REAL_CAPTURE_NADIR_DEG,
) -> None:
    """Make a scene folder from a COLMAP model with EQUIRECTANGULAR cameras (upright, metric)."""
    from pipeline.importers import import_colmap

    path = import_colmap(model_dir, images_dir, out, camera_height=camera_height, scale=scale,
                         test_every=test_every, nadir_mask_deg=nadir_mask_deg,
                         warn=lambda m: console.print(f"[yellow]warning:[/] {escape(m)}", soft_wrap=True))
    console.print(f"wrote {escape(str(path))}", soft_wrap=True)


def user_errors(fn):
    """Commands whose ValueErrors are about their arguments: report them as bad input (exit 2)."""
    import functools

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except ValueError as e:
            if isinstance(e, PanoError):
                raise
            raise PanoError(None, str(e)) from e

    return wrapper


def _register_commands() -> None:
    """Commands that live beside the package they drive."""
    from evaluation.commands import ablate_command, render_command, report_command, sweep_command
    from depthnet.command import export_depth_model_command
    from layoutnet.command import export_layout_model_command
    from export.command import export_command
    from models.command import models_app
    from pipeline.clean import clean_command
    from pipeline.new_scene import new_command
    from simulate.command import simulate_command
    from viewer.command import view_command

    app.command("new")(new_command)
    app.command("clean")(clean_command)
    app.command("simulate")(user_errors(simulate_command))
    app.command("export-layout-model")(export_layout_model_command)
    app.command("export-depth-model")(export_depth_model_command)
    app.command("report")(report_command)
    app.command("ablate")(ablate_command)
    app.command("sweep")(sweep_command)
    app.command("render")(render_command)
    app.command("view")(view_command)
    app.command("export")(export_command)
    app.add_typer(models_app, name="models")


_register_commands()


INTERRUPTED = "interrupted: finished results are kept; the unfinished one left nothing behind"


def _interrupted_inside(e: BaseException) -> bool:
    """Whether a KeyboardInterrupt (Ctrl-C, SIGTERM) caused `e`: pybind11 turns one raised while a
    native module initialises into ImportError('initialization failed')."""
    seen = set()
    while e is not None and id(e) not in seen:
        if isinstance(e, KeyboardInterrupt):
            return True
        seen.add(id(e))
        e = e.__cause__ or e.__context__
    return False


def _fail(message: str, code: int) -> None:
    """One line on stderr, never parsed as markup (user text may hold '[/b]'), then exit."""
    from rich.text import Text

    err_console.print(Text.assemble(("error:", "red"), " ", one_line(message)), soft_wrap=True)
    sys.exit(code)


def _click_exceptions(name: str) -> tuple[type, ...]:
    """click's exception class `name`, and typer's vendored copy of it (typer >= 0.2x ships its own click)."""
    import importlib

    found = []
    for module in ("click.exceptions", "typer._click.exceptions", "typer.exceptions"):
        try:
            found.append(getattr(importlib.import_module(module), name))
        except (ImportError, AttributeError):
            pass
    return tuple(found)


def _quiet_opencv() -> None:
    """OpenCV logs its own decoder errors to stderr; pano-pipe reports an unreadable file itself,
    in one line, so OpenCV's log is switched off (the environment variable before cv2 is imported,
    the call if it already is)."""
    os.environ.setdefault("OPENCV_LOG_LEVEL", "OFF")
    if "cv2" in sys.modules:
        cv2 = sys.modules["cv2"]
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)


def _quiet_warnings() -> None:
    """Library warnings (numpy's RuntimeWarnings on overflow or NaN, deprecations) are not for the
    user of a command: stderr holds the error line only, and pano-pipe reports what matters itself
    (ctx.warn, on stdout). --debug shows them."""
    import warnings

    warnings.simplefilter("ignore")


def _show_flags_as_flags(command) -> None:
    """On/off options take no value: help lists them bare (`--y-up`), not as `--y-up <bool>`
    (typer shows a type for every option; an empty metavar leaves the type column blank)."""
    def bare(param):
        if param is not None and getattr(param, "is_flag", False) and param.metavar is None:
            param.metavar = ""
        return param

    for param in command.params:
        if param.param_type_name == "option":
            bare(param)
    make_help_option = command.get_help_option  # --help is made on demand, per command
    command.get_help_option = lambda ctx: bare(make_help_option(ctx))
    for sub in getattr(command, "commands", {}).values():
        _show_flags_as_flags(sub)


#: Values a user may write after a flag, by habit from other tools (`--y-up true`).
_FLAG_VALUES = ("true", "false", "yes", "no", "on", "off", "1", "0")


def _usage_message(e) -> str:
    """click's usage error, with what to do next where the bare message leaves a newcomer stuck."""
    missing = isinstance(e, _click_exceptions("MissingParameter"))
    message = e.format_message()
    ctx = getattr(e, "ctx", None)
    command = ctx.command_path if ctx is not None else "pano-pipe"
    if missing and ctx is not None and ctx.command.name == "run":
        from pipeline.registry import build_registry
        from pipeline.engine import topological_order

        stages = ", ".join(topological_order(build_registry()))
        return (f"{message} `pano-pipe run` takes a stage and one or more scene folders, e.g. "
                f"`pano-pipe run all scenes/demo`; the stage is 'all' or one of {stages} "
                f"(`pano-pipe run --help` lists the options)")
    if missing:
        return f"{message} (`{command} --help` shows the usage)"
    import re

    extra = re.search(r"unexpected extra arguments? ?(?:\(s\))? \((.*)\)", message)
    extra = extra.group(1) if extra else ""
    args = sys.argv[1:]
    at = args.index(extra) if extra.lower() in _FLAG_VALUES and extra in args else -1
    if at > 0 and args[at - 1].startswith("--"):  # the value follows a flag
        flag = args[at - 1]
        return (f"{message}: {flag} is a flag and takes no value: write {flag} to turn it on, "
                f"leave it out to keep it off")
    return message


def main() -> None:
    """Console entry point. Exit codes: 0 success, 1 internal error, 2 bad input (one line naming
    the file and the problem), 130 interrupted (Ctrl-C or SIGTERM). --debug shows tracebacks."""
    _quiet_opencv()
    _quiet_warnings()
    signals.install()  # SIGTERM like Ctrl-C, kept across native imports (pycolmap takes it)
    try:
        command = typer.main.get_command(app)
        _show_flags_as_flags(command)
        code = command(standalone_mode=False)
        if code == 130:  # typer turns Ctrl-C into this return value, silently, when not standalone
            raise KeyboardInterrupt
        # typer returns an Exit's code instead of raising it when standalone_mode is off
        if isinstance(code, int) and code != 0:
            sys.exit(code)
    except PanoError as e:
        if _state["debug"]:
            raise
        _fail(str(e), e.exit_code)
    except SystemExit:
        raise
    except _click_exceptions("Exit") as e:
        sys.exit(e.exit_code)
    except (KeyboardInterrupt, *_click_exceptions("Abort")):
        err_console.print(INTERRUPTED)
        sys.exit(130)
    except _click_exceptions("ClickException") as e:  # usage errors: one line, bad input
        _fail(_usage_message(e), 2)
    except OSError as e:  # the environment: a full disk, a read-only folder, no permission
        if _state["debug"]:
            raise
        where = e.filename or "pano-pipe"
        _fail(f"{where}: {e.strerror or e}", 2 if e.errno is not None else 1)
    except RecursionError:
        if _state["debug"]:
            raise
        _fail("input nested too deeply (rerun with --debug for the traceback)", 2)
    except Exception as e:  # unexpected failures: a bug of ours
        if _interrupted_inside(e):  # Ctrl-C / SIGTERM inside a native import or a library that wraps it
            err_console.print(INTERRUPTED)
            sys.exit(130)
        if _state["debug"]:
            raise
        _fail(f"{type(e).__name__}: {e} (an internal error; rerun with --debug for the traceback)", 1)


if __name__ == "__main__":
    main()
