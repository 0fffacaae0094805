"""`pano-pipe models list|fetch|path` (registered by pipeline/cli.py)."""

from __future__ import annotations

from typing import Annotated

import typer

models_app = typer.Typer(
    help="Layout and depth models: list them, fetch one into the user cache, print its path.",
    no_args_is_help=True,
)


@models_app.command("list")
def list_command() -> None:
    """Known models: kind, source, licence, size, SHA-256, and whether each is in the cache."""
    from rich.markup import escape

    from models.registry import known_models
    from models.store import cache_dir, checkpoint_path, checkpoint_problem, onnx_path, onnx_problem, read_record
    from runtime.console import console

    console.print(escape(f"model cache: {cache_dir()}"), soft_wrap=True)
    for entry in known_models().values():
        pinned = read_record(entry).get("sha256")
        sha = entry.sha256 or (f"{pinned} (not published; pinned at the first fetch)" if pinned
                               else "not published (computed and pinned at the first fetch)")
        ckpt_problem = checkpoint_problem(entry)
        present = ("yes" if onnx_problem(entry) is None
                   else "checkpoint only (exported on first use)" if ckpt_problem is None
                   else f"damaged ({ckpt_problem}; `pano-pipe models fetch {entry.name}` replaces it)"
                   if checkpoint_path(entry).is_file()
                   else f"damaged export ({onnx_problem(entry)}; `pano-pipe models fetch {entry.name}` replaces it)"
                   if onnx_path(entry).is_file() else "no")
        size = f"{entry.size_mb:.0f} MB" if entry.size_mb else "size unknown"
        lines = [f"[bold]{escape(entry.name)}[/]  {entry.kind}  {size}  present: {escape(present)}"]
        if entry.description:
            lines.append(f"  {escape(entry.description)}")
        lines += [f"  source:  {escape(entry.host_name)} {escape(entry.url)}",
                  f"  licence: {escape(entry.licence)}",
                  f"  SHA-256: {sha}"]
        console.print("\n".join(lines), soft_wrap=True)
    console.print("get one: pano-pipe models fetch NAME; use it: --set layout.model=NAME (depth.model for depth)")


@models_app.command("fetch")
def fetch_command(
    name: Annotated[str, typer.Argument(help="A model name from `pano-pipe models list`.")],
    force: Annotated[bool, typer.Option("--force", help="Download and export again.")] = False,
) -> None:
    """Download NAME into the user cache, check its SHA-256, export it to ONNX (once), keep both."""
    from rich.markup import escape

    from models.download import fetch
    from runtime.console import console

    fetch(name, force=force, log=lambda m: console.print(escape(m), soft_wrap=True))


@models_app.command("path")
def path_command(name: Annotated[str, typer.Argument(help="A model name from `pano-pipe models list`.")]) -> None:
    """Print the ONNX file of NAME (exporting a cached checkpoint first); error when it is not fetched."""
    from models.registry import get_model
    from models.store import ensure_onnx

    typer.echo(str(ensure_onnx(get_model(name))))
