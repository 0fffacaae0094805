"""CLI command `pano-pipe view` (a typer-compatible function; pipeline/cli.py registers it)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Annotated

import typer
from rich.markup import escape

from runtime.console import console
from pipeline.signals import Terminated

from pipeline.options import OutOpt

# the viewer also takes a run folder: its own help for the shared argument
SceneArg = Annotated[Path, typer.Argument(
    help="Scene folder holding scene.json, or a run folder.", show_default=False)]


def view_command(
    scene: SceneArg,
    out: OutOpt = None,
    port: Annotated[int, typer.Option("--port", min=1, max=65535, help="Port to serve on.")] = 8080,
    host: Annotated[str, typer.Option(
        "--host", help="Address to listen on (0.0.0.0 for every interface; the viewer has no login).")
    ] = "127.0.0.1",
    pano_height: Annotated[int, typer.Option(
        "--pano-height", min=64, max=2048, help="Initial height of rendered panoramas (GUI slider).")] = 512,
) -> None:
    """Open the trained Gaussians, cameras, floor plan and layout cloud in the browser (viser); Ctrl-C stops."""
    from viewer.data import resolve_target
    from viewer.server import start_viewer

    target = resolve_target(scene, out)
    handle = start_viewer(target, host=host, port=port, pano_height=pano_height)
    console.print(f"[bold]viewer:[/] {escape(handle.url)}  (run folder {escape(str(handle.run_dir))}; Ctrl-C stops)")
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt as e:  # Ctrl-C is how a viewer stops (exit 0); SIGTERM exits 130, as everywhere
        console.print("viewer stopped")
        if isinstance(e, Terminated):
            raise
    finally:
        handle.stop()
