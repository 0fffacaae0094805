"""Atomic folder replacement and content hashing."""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import os
import shutil
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path

#: Name prefixes of the temporary folders atomic_folder makes beside their target.
TEMP_PREFIXES = (".tmp-", ".old-")
LOCK_NAME = ".lock"


@contextlib.contextmanager
def atomic_folder(final: Path) -> Iterator[Path]:
    """Yield a temporary sibling folder; on success it replaces `final`.

    On an exception (or Ctrl-C) the temporary folder is removed and `final` is
    left byte-identical. The swap is two renames on the same file system.
    """
    final = Path(final)
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = final.parent / f".tmp-{final.name}-{uuid.uuid4().hex[:8]}"
    tmp.mkdir()
    try:
        yield tmp
    except BaseException as e:
        with signals_held():
            shutil.rmtree(tmp, ignore_errors=True)
        if isinstance(e, OSError) and e.filename is None and e.errno is not None:
            # a write() on a full disk names no file: name the folder that was not written
            from runfs.errors import PanoError

            raise PanoError(final, f"not written: {e.strerror or e}") from e
        raise
    # the swap and the cleanup run whole: a Ctrl-C or SIGTERM meanwhile is handled right after, so
    # it never leaves the folder missing or an .old- copy behind
    with signals_held():
        old = final.parent / f".old-{final.name}-{uuid.uuid4().hex[:8]}"
        if final.exists():
            os.replace(final, old)
        os.replace(tmp, final)
        shutil.rmtree(old, ignore_errors=True)


@contextlib.contextmanager
def signals_held() -> Iterator[None]:
    """Hold SIGINT and SIGTERM back for the block (the main thread's signal mask); one that
    arrives meanwhile is handled as the block ends. Elsewhere than the main thread, a no-op."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


def atomic_write(path: Path, write: Callable[[Path], object]) -> Path:
    """Call `write(tmp)` on a hidden temporary sibling of `path` (same suffix, so writers that
    infer the format from it work), then rename it into place (creating the folder): a reader
    never sees half a file. On any failure the temporary file is removed and `path` is left as it was."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.{uuid.uuid4().hex[:8]}.tmp{path.suffix}")
    try:
        write(tmp)
        os.replace(tmp, path)
    except OSError as e:
        tmp.unlink(missing_ok=True)
        if e.filename not in (None, str(tmp)):
            raise
        # a write() on a full disk names no file; the temporary one means nothing to the user
        from runfs.errors import PanoError

        raise PanoError(path, f"not written: {e.strerror or e}") from None
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def atomic_write_text(path: Path, text: str) -> None:
    atomic_write(path, lambda tmp: tmp.write_text(text))


def sha256_file(path: Path, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def sha256_json(obj) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()


def open_no_follow(path: Path, flags: int) -> int:
    """os.open that refuses a symbolic link at `path`: a run folder's own files are written in
    place, and a planted link would carry those writes out of the folder."""
    from runfs.errors import PanoError

    try:
        return os.open(path, flags | os.O_NOFOLLOW, 0o644)
    except OSError as e:
        if e.errno == errno.ELOOP:
            raise PanoError(path, "is a symbolic link; pano-pipe writes its run files itself (remove the link)"
                            ) from None
        raise


def append_line(path: Path, line: str) -> None:
    """Append one line to a log file (never through a symbolic link)."""
    fd = open_no_follow(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT)
    with os.fdopen(fd, "a", encoding="utf-8") as f:
        f.write(line + "\n")


@contextlib.contextmanager
def run_folder_lock(folder: Path) -> Iterator[None]:
    """Hold an exclusive lock on a run folder for the life of one run. A second process on the
    same folder is refused at once with a one-line error. The kernel releases the lock when the
    process ends, however it ends, so a killed run never leaves a stale lock behind."""
    import fcntl

    from runfs.errors import PanoError

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    lock_path = folder / LOCK_NAME
    fd = open_no_follow(lock_path, os.O_RDWR | os.O_CREAT)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as e:
            if e.errno not in (errno.EAGAIN, errno.EACCES):
                raise
            holder = os.pread(fd, 64, 0).decode(errors="replace").strip() or "?"
            raise PanoError(folder, f"in use by another pano-pipe run (pid {holder}); wait for it to "
                                    "finish, or choose another --out") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        yield
    finally:
        os.close(fd)  # closing the descriptor releases the lock


def remove_stale_temporaries(folder: Path, stage: str | None = None) -> list[Path]:
    """Delete what interrupted runs left in a run folder (call it under the folder's lock):
    atomic_folder's `.tmp-*` / `.old-*` siblings and half-written `*.tmp` files of the scratch space;
    with `stage`, only that stage's (others may be running beside it in a batch)."""
    folder = Path(folder)
    prefixes = TEMP_PREFIXES if stage is None else tuple(f"{p}{stage}-" for p in TEMP_PREFIXES)
    removed = []
    for p in folder.iterdir() if folder.is_dir() else ():
        if p.name.startswith(prefixes) and p.is_dir() and not p.is_symlink():
            shutil.rmtree(p, ignore_errors=True)
            removed.append(p)
    scratch = folder / ".scratch" if stage is None else folder / ".scratch" / stage
    if scratch.is_dir() and not scratch.is_symlink():
        for p in scratch.rglob("*.tmp"):
            if p.is_file() and not p.is_symlink():
                p.unlink(missing_ok=True)
                removed.append(p)
    return removed


@contextlib.contextmanager
def native_stderr_off() -> Iterator[None]:
    """File descriptor 2 pointed at /dev/null for the block: native libraries (libpng, OpenCV,
    open3d's RPly) write their own messages there, hundreds of lines on a full disk, which the
    one-line error contract does not allow; pano-pipe names the file itself."""
    import sys

    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError):
        yield
        return
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 2)
    os.close(devnull)
    try:
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def native_write(path: Path, write: Callable[[], bool], what: str = "file") -> None:
    """Run a native library's writer (cv2.imwrite, open3d's write_point_cloud: they return False on
    failure and print on fd 2) with its messages kept off stderr; a failure is one PanoError
    naming the file."""
    from runfs.errors import PanoError

    with native_stderr_off():
        ok = write()
    if not ok:
        raise PanoError(path, f"could not write the {what} (a full disk, or no permission?)")
