"""SIGTERM handled like Ctrl-C by every command, whatever native library loads later.

A native library may install its own C-level signal handlers when it is imported: pycolmap
(COLMAP's glog `InstallFailureSignalHandler`) takes SIGTERM, so a `kill` then printed glog's
35-line stack dump, exited 143 and left `.tmp-*` folders behind. Python still *reports* its own
handler (`signal.getsignal`) but the kernel calls glog's. `guard_imports()`, called by the CLI
before it imports anything else, adds an import hook that holds SIGINT/SIGTERM back (the main
thread's signal mask) while each top-level module from a file loads and re-installs Python's
handlers after it, so a library imported in the middle of a command (pycolmap, when the poses
stage runs structure from motion) cannot take them, and a signal sent mid-import is handled by
ours once the import ends. Native worker threads that an import starts (OpenBLAS with numpy,
OpenCV's pool) inherit the held-back mask, so no thread but the main one takes the signal while
a later import holds it back. `install()` sets our SIGTERM handler. The cost: two `sigprocmask`
and one `sigaction` per handled signal, once per newly imported package.
"""

from __future__ import annotations

import contextlib
import importlib.abc
import signal
import sys
import threading

#: Signals whose Python handlers are put back after each import.
HANDLED = tuple(getattr(signal, name) for name in ("SIGINT", "SIGTERM") if hasattr(signal, name))


class Terminated(KeyboardInterrupt):
    """SIGTERM, handled like Ctrl-C: stages clean up, training checkpoints, exit code 130."""


def on_sigterm(signum, frame) -> None:
    raise Terminated()


def restore_handlers() -> None:
    """Re-install, at the C level, the handler Python believes each handled signal has (a
    native import may have replaced it underneath). Only the main thread may set handlers."""
    if threading.current_thread() is not threading.main_thread():
        return
    for sig in HANDLED:
        handler = signal.getsignal(sig)
        if handler is not None:  # None: a handler not set from Python; nothing of ours to restore
            signal.signal(sig, handler)


@contextlib.contextmanager
def _handlers_kept():
    """Hold the handled signals back while a module loads, then restore the handlers and let a
    pending signal through: one sent mid-import meets our handler, never the library's."""
    main = threading.current_thread() is threading.main_thread()
    old = signal.pthread_sigmask(signal.SIG_BLOCK, HANDLED) if main else None
    try:
        yield
    finally:
        restore_handlers()
        if old is not None:
            signal.pthread_sigmask(signal.SIG_SETMASK, old)


class _RestoringLoader(importlib.abc.Loader):
    """A loader that runs another one with the handled signals held back, then restores them."""

    def __init__(self, loader):
        self._loader = loader

    def create_module(self, spec):
        with _handlers_kept():  # a single-phase extension module initialises here
            return self._loader.create_module(spec)

    def exec_module(self, module) -> None:
        with _handlers_kept():
            self._loader.exec_module(module)

    def __getattr__(self, name):  # get_source, get_resource_reader, is_package, ...
        return getattr(self._loader, name)


class _RestoreAfterImport(importlib.abc.MetaPathFinder):
    """Finds top-level modules with the other finders and wraps their loader (_RestoringLoader)."""

    def __init__(self):
        self._finding = threading.local()

    def find_spec(self, name, path, target=None):
        if "." in name or getattr(self._finding, "active", False):
            return None
        self._finding.active = True
        try:
            for finder in sys.meta_path:
                find = getattr(finder, "find_spec", None)
                if finder is self or find is None:
                    continue
                spec = find(name, path, target)
                if spec is not None:
                    break
            else:
                return None
        finally:
            self._finding.active = False
        if spec.loader is None or not spec.has_location or not hasattr(spec.loader, "exec_module"):
            return spec  # namespace packages, built-in and frozen modules: no native code of theirs
        spec.loader = _RestoringLoader(spec.loader)
        return spec


_hook = _RestoreAfterImport()


def guard_imports() -> None:
    """Hold the handled signals back during every later top-level import (see the module
    docstring). Called first thing by the CLI, so that the threads native libraries start while
    they load never take SIGTERM. A no-op outside the main thread."""
    if threading.current_thread() is threading.main_thread() and _hook not in sys.meta_path:
        sys.meta_path.insert(0, _hook)


def install() -> None:
    """SIGTERM raises `Terminated`; handlers survive later native imports. Idempotent; a no-op
    outside the main thread (signal handlers can only be set there)."""
    if threading.current_thread() is not threading.main_thread():
        return
    signal.signal(signal.SIGTERM, on_sigterm)
    guard_imports()
