"""`pano-pipe`: the command line (typer).

Every user-facing failure is one line on stderr and exit code 2; `--debug`
shows the traceback instead.
"""

from __future__ import annotations

import os

# OpenMP threads that busy-wait between parallel regions made 2 threads 10x slower
# than 1 on a shared 2-core machine (docs/training.md); must be set before torch loads.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import json  # noqa: E402
import shutil
import sys
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.table import Table

from pipeline.console import console
from pipeline.errors import PanoError

app = typer.Typer(
    name="pano-pipe",
    help="Indoor 360° panoramas to a Gaussian Splatting model (360-GS, layout-guided).",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
bench_app = typer.Typer(help="Benchmarks: what accuracy costs in time.", no_args_is_help=True)
app.add_typer(bench_app, name="bench")

_state = {"debug": False}

SceneArg = Annotated[Path, typer.Argument(help="Scene folder holding scene.json.", show_default=False)]
OutOpt = Annotated[
    Optional[Path], typer.Option("--out", help="Run folder (default: runs/<scene-name>/).")
]
ConfigOpt = Annotated[
    Optional[Path], typer.Option("--config", help="YAML or JSON file of stage parameters: {stage: {param: value}}.")
]
SetOpt = Annotated[
    Optional[list[str]], typer.Option("--set", help="Override one parameter: STAGE.PARAM=VALUE (repeatable).")
]


@app.callback()
def _main(debug: Annotated[bool, typer.Option("--debug", help="Show tracebacks.")] = False) -> None:
    _state["debug"] = debug


# -- helpers ------------------------------------------------------------------
def load_config(path: Path | None, overrides: list[str] | None) -> tuple[dict[str, dict], str]:
    """Stage parameters from a YAML/JSON file plus `--set stage.param=value` overrides."""
    config: dict[str, dict] = {}
    source = "--set"
    if path is not None:
        source = str(path)
        if not path.is_file():
            raise PanoError(path, "config file does not exist")
        import yaml  # JSON is YAML, so one parser reads both

        try:
            loaded = yaml.safe_load(path.read_text()) or {}
        except yaml.YAMLError as e:
            raise PanoError(path, f"not valid YAML/JSON: {str(e).splitlines()[0]}") from None
        if not isinstance(loaded, dict) or not all(isinstance(v, dict) for v in loaded.values()):
            raise PanoError(path, "expected a mapping {stage: {param: value}}")
        config = {k: dict(v) for k, v in loaded.items()}
    for item in overrides or []:
        import yaml

        lhs, sep, value = item.partition("=")
        stage, dot, param = lhs.partition(".")
        if not sep or not dot or not stage or not param:
            raise PanoError("--set", f"{item!r} is not STAGE.PARAM=VALUE")
        config.setdefault(stage, {})[param] = yaml.safe_load(value)
    return config, source


def make_engine(scene_dir: Path, out: Path | None, config_file: Path | None, overrides: list[str] | None):
    from pipeline.engine import Engine
    from pipeline.registry import build_registry
    from pipeline.scene_loader import load_scene

    scene = load_scene(scene_dir)
    config, source = load_config(config_file, overrides)
    out_dir = out if out is not None else Path("runs") / scene.name
    return Engine(scene, out_dir, build_registry(), config, config_source=source)


def print_status_table(engine) -> None:
    plans = engine.plan()
    table = Table(title=f"{engine.scene.name} → {engine.out_dir}")
    for col in ("stage", "state", "last duration", "note"):
        table.add_column(col)
    colours = {"up-to-date": "green", "stale": "yellow", "missing": "red", "skipped": "dim"}
    for name in engine.order:
        p = plans[name]
        dur = f"{p.last_duration_s:.2f} s" if p.last_duration_s is not None else "—"
        table.add_row(name, f"[{colours[p.state]}]{p.state}[/]", dur, p.reason)
    console.print(table)


# -- commands -----------------------------------------------------------------
@app.command()
def run(
    stage: Annotated[str, typer.Argument(help="A stage name, or 'all'.")],
    scene: SceneArg,
    out: OutOpt = None,
    config: ConfigOpt = None,
    set_: SetOpt = None,
    force: Annotated[bool, typer.Option("--force", help="Rerun every selected stage, cached or not.")] = False,
    until: Annotated[Optional[str], typer.Option("--until", help="Stop after this stage.")] = None,
    resume: Annotated[bool, typer.Option("--resume", help="Continue training from its last checkpoint.")] = False,
) -> None:
    """Run the pipeline (`all`) or one stage (rerun, with anything stale upstream)."""
    engine = make_engine(scene, out, config, set_)
    target = None if stage == "all" else stage
    if target is not None and target not in engine.registry:
        raise PanoError(None, f"unknown stage {stage!r}; choose 'all' or one of {', '.join(engine.order)}")
    results = engine.run(target=target, until=until, force=force, resume=resume)
    table = Table(title="run")
    for col in ("stage", "outcome", "seconds", "note"):
        table.add_column(col)
    for r in results:
        table.add_row(r.name, r.outcome, f"{r.duration_s:.2f}" if r.outcome == "ran" else "", r.reason)
    console.print(table)
    evaluated = engine.out_dir / "evaluate" / "artifact.json"
    if any(r.name == "evaluate" and r.outcome in ("ran", "cached") for r in results) and evaluated.is_file():
        data = json.loads(evaluated.read_text())["data"]
        mean = data.get("mean", {})
        shown = ", ".join(f"{k} {v:.4g}" for k, v in mean.items() if isinstance(v, (int, float)))
        console.print(f"[bold]test metrics:[/] {shown}")


@app.command()
def status(scene: SceneArg, out: OutOpt = None, config: ConfigOpt = None, set_: SetOpt = None) -> None:
    """Each stage's state (up-to-date / stale / missing / skipped and why) and last duration."""
    print_status_table(make_engine(scene, out, config, set_))


@app.command()
def clean(scene: SceneArg, out: OutOpt = None) -> None:
    """Delete the scene's run folder."""
    from pipeline.scene_loader import load_scene

    s = load_scene(scene, check_images=False)
    out_dir = out if out is not None else Path("runs") / s.name
    if out_dir.exists():
        shutil.rmtree(out_dir)
        console.print(f"removed {out_dir}")
    else:
        console.print(f"nothing to clean: {out_dir} does not exist")


@app.command()
def schema(out: Annotated[Path, typer.Argument(help="Folder to write the JSON Schemas into.")]) -> None:
    """Write the JSON Schema of scene.json and of every stage artifact."""
    from schemas import all_schemas

    out.mkdir(parents=True, exist_ok=True)
    for name, model in all_schemas().items():
        (out / f"{name}.schema.json").write_text(json.dumps(model.model_json_schema(), indent=2))
        console.print(f"wrote {out / (name + '.schema.json')}")


@app.command("import-nerfstudio")
def import_nerfstudio_command(
    transforms: Annotated[Path, typer.Argument(help="nerfstudio transforms.json (EQUIRECTANGULAR).")],
    out: Annotated[Path, typer.Argument(help="Scene folder to write.")],
    world_up: Annotated[str, typer.Option(help="Up axis of the nerfstudio world: +z, +y or -y.")] = "+z",
    test_every: Annotated[int, typer.Option(help="Every Nth frame is a test view (0: none).")] = 8,
) -> None:
    """Make a scene folder from a nerfstudio transforms.json."""
    from pipeline.importers import import_nerfstudio

    path = import_nerfstudio(transforms, out, world_up=world_up, test_every=test_every)
    console.print(f"wrote {path}")


@bench_app.command("render")
def bench_render(
    quick: Annotated[bool, typer.Option(help="A small grid (128x256 and 512x1024; 20k and 100k).")] = False,
    resolutions: Annotated[str, typer.Option(help="HxW list.")] = "128x256,256x512,512x1024",
    counts: Annotated[str, typer.Option(help="Gaussian counts.")] = "20000,100000,300000",
    backends: Annotated[str, typer.Option(help="cpp,torch")] = "cpp,torch",
    repeats: Annotated[int, typer.Option(help="Timed repeats (median).")] = 3,
    out_json: Annotated[Path, typer.Option(help="JSON result.")] = Path("docs/bench_render.json"),
    out_md: Annotated[Path, typer.Option(help="Markdown table.")] = Path("docs/bench_render.md"),
) -> None:
    """Renderer speed, memory, cubemap baseline and tangent-plane accuracy, per backend."""
    from splatting.bench import main as bench_main

    bench_main(
        [
            "--resolutions", resolutions, "--counts", counts, "--backends", backends,
            "--repeats", str(repeats), "--out-json", str(out_json), "--out-md", str(out_md),
            *(["--quick"] if quick else []),
        ]
    )


@bench_app.command("pipeline")
def bench_pipeline_command(
    scene: Annotated[Optional[Path], typer.Argument(help="Scene (default: a fresh `demo` scene).")] = None,
    config: ConfigOpt = None,
    set_: SetOpt = None,
    out_json: Annotated[Path, typer.Option(help="JSON result.")] = Path("docs/bench_pipeline.json"),
    out_md: Annotated[Path, typer.Option(help="Markdown table.")] = Path("docs/bench_pipeline.md"),
) -> None:
    """Time a full run and a second, cached run of the same scene."""
    from pipeline.benchmarks import bench_pipeline

    cfg, _ = load_config(config, set_)
    bench_pipeline(scene, cfg, out_md, out_json)


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
    from layoutnet.command import export_layout_model_command
    from simulate.command import simulate_command

    app.command("simulate")(user_errors(simulate_command))
    app.command("export-layout-model")(export_layout_model_command)
    app.command("report")(report_command)
    app.command("ablate")(ablate_command)
    app.command("sweep")(sweep_command)
    app.command("render")(render_command)


_register_commands()


def main() -> None:
    """Console entry point: one-line errors with exit code 2 unless --debug."""
    try:
        app(standalone_mode=False)
    except PanoError as e:
        if _state["debug"]:
            raise
        console.print(f"[red]error:[/] {e}", soft_wrap=True)
        sys.exit(e.exit_code)
    except (typer.Exit, SystemExit) as e:
        code = getattr(e, "exit_code", getattr(e, "code", 0))
        sys.exit(code)
    except KeyboardInterrupt:
        console.print("[red]interrupted[/]: finished stages are kept, the running one left its old result")
        sys.exit(130)
    except Exception as e:  # click usage errors and unexpected failures
        import click

        if isinstance(e, click.exceptions.ClickException):
            e.show()
            sys.exit(2)
        if isinstance(e, click.exceptions.Abort):
            sys.exit(130)
        if _state["debug"]:
            raise
        console.print(f"[red]error:[/] {type(e).__name__}: {e} (rerun with --debug for the traceback)", soft_wrap=True)
        sys.exit(1)


if __name__ == "__main__":
    main()
