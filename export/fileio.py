"""Output paths and atomic writes for the export command."""

from __future__ import annotations

import os
import uuid
from collections.abc import Callable
from pathlib import Path

from pipeline.errors import PanoError


def temp_sibling(path: Path) -> Path:
    """A hidden, unique temporary name beside `path` (same file system, so os.replace is atomic)."""
    path = Path(path)
    return path.with_name(f".{path.stem}.{uuid.uuid4().hex[:8]}.tmp{path.suffix}")


def check_writable(path: Path, overwrite: bool) -> None:
    """Refuse an existing output (unless `overwrite`), a folder or a symbolic link in its place."""
    path = Path(path)
    if path.is_symlink():
        raise PanoError(path, "is a symbolic link; choose another --out")
    if path.is_dir():
        raise PanoError(path, "is a folder; --out names the file to write")
    if path.exists() and not overwrite:
        raise PanoError(path, "already exists; pass --overwrite to replace it, or choose another --out")


def atomic_write(path: Path, write: Callable[[Path], object]) -> Path:
    """Call `write(tmp)` on a temporary sibling of `path`, then rename it into place.
    On any failure the temporary file is removed and `path` is left as it was."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_sibling(path)
    try:
        write(tmp)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def atomic_write_bytes(path: Path, data: bytes) -> Path:
    return atomic_write(path, lambda tmp: Path(tmp).write_bytes(data))
