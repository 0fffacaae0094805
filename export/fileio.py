"""Output paths of the export command (files are written with runfs.fsutil.atomic_write)."""

from __future__ import annotations

from pathlib import Path

from runfs.errors import PanoError


def check_writable(path: Path, overwrite: bool) -> None:
    """Refuse an existing output (unless `overwrite`), a folder or a symbolic link in its place."""
    path = Path(path)
    if path.is_symlink():
        raise PanoError(path, "is a symbolic link; choose another --out")
    if path.is_dir():
        raise PanoError(path, "is a folder; --out names the file to write")
    if path.exists() and not overwrite:
        raise PanoError(path, "already exists; pass --overwrite to replace it, or choose another --out")
