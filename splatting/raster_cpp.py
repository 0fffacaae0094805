"""The compiled CPU backend: a torch C++ extension (OpenMP), built once per machine.

The build is cached in ``$PANO_PIPE_CACHE`` (default ``$XDG_CACHE_HOME/pano-pipe``, else
``~/.cache/pano-pipe``: runfs.cache) under
``splatting-<key>``, the key hashing everything the binary depends on: the sources,
the compiler flags, the compiler (``$CXX`` or ``c++``, and its ``--version``), the torch
version *and install folder* (its headers and libraries are absolute paths in the build),
the Python version and the CPU model (``-march=native``, or ``$PANO_PIPE_MARCH``). A changed kernel, compiler,
virtual environment or machine therefore builds its own folder, never rewrites another's.

Several processes may load or build at once (two test suites, a test suite and a
``pano-pipe run``, two checkouts with their own venvs):

* a published ``splatting-<key>/`` folder is complete and never modified: it appears in
  one ``rename`` of a private build folder, so a reader sees the finished ``.so`` or no
  folder at all, and nothing rewrites a ``.so`` another process has mapped;
* only one process builds a key at a time: an exclusive ``flock`` on
  ``splatting-<key>.lock`` in the cache root. The kernel drops it when the holder exits,
  however it exits (SIGKILL included), so a killed build leaves no lock that blocks later
  processes (torch's own ``lock`` file baton, which stays forever after a killed builder,
  is only ever used inside the private build folder). The others wait, up to
  ``$PANO_PIPE_BUILD_WAIT`` seconds (default 1800), then load what was published;
* leftovers of killed builds (``splatting-<key>.build-*``) are removed by the next
  builder of that key, which holds the lock, so none of them can be in use.

If the build fails (no compiler, no ninja) a warning is given once and ``render``
falls back to the torch backend.
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib.util
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import threading
import time
import warnings
from pathlib import Path

import torch

from .project import DEPTH_KEY_SHIFT

try:
    import fcntl
except ImportError:  # pragma: no cover - not POSIX: no inter-process lock, publishing stays atomic
    fcntl = None

_SRC = Path(__file__).parent / "csrc" / "splat_cpu.cpp"
# -march: this machine's instruction set by default; $PANO_PIPE_MARCH names another (e.g.
# x86-64-v3 for a build shared by machines with and without AVX-512)
_MARCH = os.environ.get("PANO_PIPE_MARCH", "native")
# the depth order's key is defined once, in splatting/project.py
_CFLAGS = ["-O3", "-fopenmp", f"-march={_MARCH}", "-fno-math-errno", f"-DDEPTH_KEY_SHIFT={DEPTH_KEY_SHIFT}"]
_LDFLAGS = ["-fopenmp"]
_LIB_EXT = ".pyd" if sys.platform == "win32" else ".so"  # what cpp_extension names the library
_WAIT_ENV = "PANO_PIPE_BUILD_WAIT"
_WAIT_DEFAULT_S = 1800.0
_lock = threading.Lock()
_module = None
_failed = False


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name") or line.startswith("flags"):
                    return line
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _compiler_id() -> str:
    """The compiler cpp_extension will call (``$CXX`` or ``c++``) and its version banner."""
    cxx = os.environ.get("CXX", "c++")
    try:
        out = subprocess.run([cxx, "--version"], capture_output=True, text=True, timeout=60)
        banner = out.stdout.strip().splitlines()[0] if out.stdout.strip() else ""
    except (OSError, subprocess.SubprocessError):
        banner = "unavailable"
    return f"{cxx}|{shutil.which(cxx) or ''}|{banner}"


def cache_root() -> Path:
    from runfs.cache import user_cache_root  # the model cache's root too: one rule for both

    return user_cache_root()


def build_dir() -> Path:
    """``<cache>/splatting-<key>``: the published build for this source, toolchain, torch and machine."""
    h = hashlib.sha256()
    for f in sorted(_SRC.parent.glob("*")):
        if f.suffix in (".cpp", ".h"):
            h.update(f.name.encode())
            h.update(f.read_bytes())
    for part in (
        torch.__version__,
        os.path.realpath(os.path.dirname(torch.__file__)),
        " ".join(_CFLAGS),
        " ".join(_LDFLAGS),
        _compiler_id(),
        _cpu_model(),
        sys.version,
        sys.implementation.cache_tag or "",
    ):
        h.update(b"\0" + str(part).encode())
    return cache_root() / f"splatting-{h.hexdigest()[:16]}"


def module_name(bdir: Path) -> str:
    return "pano_splat_cpu_" + bdir.name.split("-")[-1]


def _import_library(name: str, path: Path):
    spec = importlib.util.spec_from_file_location(name, path)
    if spec is None or spec.loader is None:
        raise ImportError(f"cannot load {path}")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@contextlib.contextmanager
def build_lock(path: Path, wait_s: float | None = None):
    """Exclusive ``flock`` on ``path`` (created if missing, never deleted), polled up to ``wait_s``.

    The lock belongs to the open file description, so the kernel releases it when the
    holder exits for any reason: a stale lock file is just a file, never a held lock.
    """
    if wait_s is None:
        wait_s = float(os.environ.get(_WAIT_ENV, _WAIT_DEFAULT_S))
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        if fcntl is not None:
            t0 = time.monotonic()
            told = False
            while True:
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                    break
                except BlockingIOError:
                    waited = time.monotonic() - t0
                    if waited > wait_s:
                        raise TimeoutError(
                            f"another process held {path} for more than {wait_s:.0f} s "
                            f"(holder: {_lock_holder(path)}; ${_WAIT_ENV} sets the wait)"
                        ) from None
                    if not told and waited > 2.0:
                        print(f"splatting: waiting for another process ({_lock_holder(path)}) "
                              f"compiling the C++ kernel ({path})...", file=sys.stderr, flush=True)
                        told = True
                    time.sleep(0.25)
            os.ftruncate(fd, 0)
            os.write(fd, f"pid {os.getpid()} on {platform.node()}\n".encode())
        yield
    finally:
        os.close(fd)  # releases the flock


def _lock_holder(path: Path) -> str:
    try:
        return path.read_text().strip() or "unknown pid"
    except OSError:
        return "unknown pid"


def _remove_tree(p: Path) -> None:
    """Delete a folder nobody uses: renamed aside first, so a half-deleted tree never keeps its name."""
    if not p.exists():
        return
    trash = p.with_name(f"{p.name}.trash-{os.getpid()}-{time.monotonic_ns()}")
    try:
        os.rename(p, trash)
    except OSError:
        trash = p
    shutil.rmtree(trash, ignore_errors=True)


def _build_and_publish(bdir: Path, name: str):
    """Compile into a private folder beside ``bdir``, then rename it to ``bdir`` (under the lock)."""
    from torch.utils import cpp_extension

    root = bdir.parent
    for old in root.glob(f"{bdir.name}.build-*"):  # killed builders' leftovers: we hold the lock
        _remove_tree(old)
    for old in root.glob(f"{bdir.name}.trash-*"):
        shutil.rmtree(old, ignore_errors=True)
    if bdir.exists():  # not published by us (published folders always hold the library): set aside
        _remove_tree(bdir)
    tmp = Path(tempfile.mkdtemp(prefix=f"{bdir.name}.build-", dir=root))
    try:
        module = cpp_extension.load(
            name=name, sources=[str(_SRC)], extra_cflags=_CFLAGS, extra_ldflags=_LDFLAGS,
            build_directory=str(tmp), verbose=False,
        )
        lib = Path(getattr(module, "__file__", "") or "")
        if lib != tmp / (name + _LIB_EXT) or not lib.is_file():
            # cpp_extension renamed it (a second build of `name` in this process): use, don't publish.
            return module
        with open(lib, "rb") as fh:  # on disk before the folder gets its public name
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o755)  # mkdtemp made it private; the cache may be shared
        try:
            os.rename(tmp, bdir)
        except OSError:
            if not (bdir / lib.name).is_file():
                raise
            # published meanwhile (possible only without flock): keep theirs, use ours
        else:
            tmp = None
        return module
    finally:
        if tmp is not None:
            _remove_tree(tmp)


def _load_or_build():
    bdir = build_dir()
    name = module_name(bdir)
    lib = bdir / (name + _LIB_EXT)
    if lib.is_file():  # published, hence complete and never rewritten: no lock needed
        try:
            return _import_library(name, lib)
        except (ImportError, OSError) as exc:
            raise ImportError(f"{lib}: {exc} (delete {bdir} to rebuild it)") from exc
    bdir.parent.mkdir(parents=True, exist_ok=True)
    with build_lock(bdir.parent / f"{bdir.name}.lock"):
        if lib.is_file():  # another process published it while we waited
            return _import_library(name, lib)
        print(f"splatting: compiling the C++ CPU kernel once into {bdir} (about a minute)...",
              file=sys.stderr, flush=True)
        module = _build_and_publish(bdir, name)
        print("splatting: C++ kernel ready.", file=sys.stderr, flush=True)
        return module


def load():
    """The compiled module, or None (after one warning) if it cannot be built."""
    global _module, _failed
    if _module is not None or _failed:
        return _module
    with _lock:
        if _module is not None or _failed:
            return _module
        try:
            _module = _load_or_build()
        except Exception as exc:  # noqa: BLE001 - any build failure means "fall back"
            _failed = True
            warnings.warn(
                f"splatting: could not build the C++ CPU kernel ({type(exc).__name__}: {exc}); "
                "falling back to the (slower) torch backend.",
                RuntimeWarning,
                stacklevel=2,
            )
    return _module


def available() -> bool:
    return load() is not None


def is_built() -> bool:
    """Whether `load` needs no build: loaded already, failed already, or a published build exists."""
    if _module is not None or _failed:
        return True
    bdir = build_dir()
    return (bdir / (module_name(bdir) + _LIB_EXT)).is_file()


def camera_vector(camera, eps2d, near):
    from .cameras import EquirectCamera

    sx, sy = camera.pixel_scale
    if isinstance(camera, EquirectCamera):
        kind, cx, cy = 0.0, 0.0, 0.0
    else:
        kind, cx, cy = 1.0, float(camera.cx), float(camera.cy)
    return torch.tensor([kind, camera.height, camera.width, sx, sy, cx, cy, float(eps2d), float(near)],
                        dtype=torch.float64)


class CppRender(torch.autograd.Function):
    """Projection, sorting, binning and rasterisation fused in C++ (forward and backward).

    ``means2d`` only carries the gradient: the splat centres are offset by
    ``means2d − means2d.detach()`` (zero) in the tangent plane, so its gradient is the
    tangent-plane position gradient, its value is not used.
    """

    @staticmethod
    def forward(ctx, means, quats, scales, opac, rgb, viewmat, means2d, dirs, camv, ts):
        m = load()
        res = m.render_forward(means.contiguous(), quats.contiguous(), scales.contiguous(), opac.contiguous(),
                               rgb.contiguous(), viewmat.contiguous(), dirs, camv, ts)
        color, depth, Tf, last, P, bbox, toff, tlist, valid, radii, m2d, rot, hit = res
        ctx.save_for_backward(means, quats, scales, opac, viewmat, dirs, camv, P, bbox, toff, tlist, Tf, last,
                              valid, rot, hit)
        ctx.ts = ts
        ctx.mark_non_differentiable(valid, radii, m2d)
        return color, depth, 1.0 - Tf, valid, radii, m2d

    @staticmethod
    def backward(ctx, g_color, g_depth, g_alpha, *_):
        means, quats, scales, opac, viewmat, dirs, camv, P, bbox, toff, tlist, Tf, last, valid, rot, hit = ctx.saved_tensors
        dt = means.dtype
        H, W = int(camv[1]), int(camv[2])

        def prep(g, shape):
            return torch.zeros(shape, dtype=dt) if g is None else g.to(dt).contiguous()

        gm, gq, gs, go, grgb, gv, gm2d = load().render_backward(
            prep(g_color, (H, W, 3)), prep(g_depth, (H, W)), prep(g_alpha, (H, W)),
            means.contiguous(), quats.contiguous(), scales.contiguous(), opac.contiguous(), viewmat.contiguous(),
            dirs, camv, ctx.ts, P, bbox, toff, tlist, Tf, last, valid, rot, hit,
        )
        return gm, gq, gs, go, grgb, gv, gm2d, None, None, None


_DIRS_CACHE: dict = {}


def pixel_planes(camera, dtype):
    """[3,H,W] ray directions, cached per camera (they are recomputed on every call otherwise)."""
    key = (camera, dtype)
    d = _DIRS_CACHE.get(key)
    if d is None:
        if len(_DIRS_CACHE) > 16:
            _DIRS_CACHE.clear()
        d = camera.pixel_dirs(dtype=dtype).permute(2, 0, 1).contiguous()
        _DIRS_CACHE[key] = d
    return d
