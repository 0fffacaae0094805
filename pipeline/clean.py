"""`pano-pipe clean SCENE`: delete the scene's run folder, after saying what goes and asking.

A run can hold hours of training, so deleting it is confirmed: on a terminal by a y/N
question, elsewhere (a script, CI) only with `--yes`; `--dry-run` lists what would go and
deletes nothing. Every check on the folder (a run folder of this scene, not a link) comes
before the question.
"""

from __future__ import annotations

import os
import shutil
import sys
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.markup import escape

from runtime.console import console
from runfs.errors import PanoError


def _size(path: Path) -> tuple[int, int]:
    """(files, bytes) under `path`, links counted as themselves, never followed."""
    if path.is_symlink() or not path.is_dir():
        return 1, path.lstat().st_size
    files = size = 0
    for root, _, names in os.walk(path):
        for name in names:
            files += 1
            size += (Path(root) / name).lstat().st_size
    return files, size


def _megabytes(n: int) -> str:
    return f"{n / 1e6:.1f} MB"


def clean_command(
    scene: Annotated[Path, typer.Argument(help="Scene folder holding scene.json.", show_default=False)],
    out: Annotated[Optional[Path], typer.Option("--out", help="Run folder (default: runs/<scene-name>/).")] = None,
    yes: Annotated[bool, typer.Option("--yes", "-y", help="Delete without asking (needed without a terminal).")]
    = False,
    dry_run: Annotated[bool, typer.Option("--dry-run", help="List what would be deleted; delete nothing.")] = False,
) -> None:
    """Delete the scene's run folder (asks first; --yes to skip the question, --dry-run to list it)."""
    from runfs.fsutil import LOCK_NAME, run_folder_lock
    from runfs.paths import check_run_folder, default_run_folder, is_run_folder
    from schemas.scene_loader import load_scene

    s = load_scene(scene, check_images=False)
    out_dir = out if out is not None else default_run_folder(s.name, s.root)
    if not out_dir.exists():
        console.print(f"nothing to clean: {escape(str(out_dir))} does not exist", soft_wrap=True)
        return
    if out_dir.is_symlink():  # deleting through it would empty the target and leave the link
        raise PanoError(out_dir, f"is a symbolic link (to {os.readlink(out_dir)}); name the run folder itself")
    check_run_folder(out_dir, s.root, links_ok=True)
    if not is_run_folder(out_dir):  # an empty folder: nothing of ours to delete
        console.print(f"nothing to clean: {escape(str(out_dir))} holds no pano-pipe run", soft_wrap=True)
        return
    entries = sorted(out_dir.iterdir())
    sizes = {child: _size(child) for child in entries}
    total = sum(b for _, b in sizes.values())
    summary = f"{out_dir} ({sum(f for f, _ in sizes.values())} files, {_megabytes(total)})"
    if dry_run:
        console.print(escape(f"would delete {summary}:"), soft_wrap=True)
        for child, (files, size) in sizes.items():
            console.print(escape(f"  {child.name}{'/' if child.is_dir() else ''}  {files} files, "
                                 f"{_megabytes(size)}"), soft_wrap=True)
        return
    if not yes:
        if not sys.stdin.isatty():
            raise PanoError(out_dir, "not deleted: no terminal to ask on; add --yes to delete it "
                                     "(--dry-run lists what it holds)")
        if not typer.confirm(f"delete {summary}?", default=False):
            console.print("nothing deleted")
            return
    with run_folder_lock(out_dir):
        for child in out_dir.iterdir():  # the lock file last: it is held until the end
            if child.name != LOCK_NAME:
                shutil.rmtree(child) if child.is_dir() and not child.is_symlink() else child.unlink()
    (out_dir / LOCK_NAME).unlink(missing_ok=True)
    out_dir.rmdir()
    console.print(f"removed {escape(str(out_dir))}", soft_wrap=True)
