"""The compiled CPU backend: a torch C++ extension (OpenMP), built once per machine.

The build is cached in ``$PANO_PIPE_CACHE`` (default ``~/.cache/pano-pipe``) under
``splatting-<hash>``, the hash covering the source, the torch version, the compiler
flags and the CPU model, so a changed kernel or machine rebuilds by itself. If the
build fails (no compiler, no ninja) a warning is given once and ``render`` falls
back to the torch backend.
"""

from __future__ import annotations

import hashlib
import os
import platform
import sys
import threading
import warnings
from pathlib import Path

import torch

_SRC = Path(__file__).parent / "csrc" / "splat_cpu.cpp"
_CFLAGS = ["-O3", "-fopenmp", "-march=native", "-fno-math-errno"]
_LDFLAGS = ["-fopenmp"]
_lock = threading.Lock()
_module = None
_failed = False


def _cpu_model() -> str:
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name") or line.startswith("flags"):
                return line
    except OSError:
        pass
    return platform.processor() or platform.machine()


def build_dir() -> Path:
    h = hashlib.sha256()
    for f in sorted(_SRC.parent.glob("*")):
        if f.suffix in (".cpp", ".h"):
            h.update(f.name.encode())
            h.update(f.read_bytes())
    h.update(torch.__version__.encode())
    h.update(" ".join(_CFLAGS).encode())
    h.update(_cpu_model().encode())
    h.update(sys.version.encode())
    root = Path(os.environ.get("PANO_PIPE_CACHE", Path.home() / ".cache" / "pano-pipe"))
    return root / f"splatting-{h.hexdigest()[:16]}"


def load():
    """The compiled module, or None (after one warning) if it cannot be built."""
    global _module, _failed
    if _module is not None or _failed:
        return _module
    with _lock:
        if _module is not None or _failed:
            return _module
        try:
            from torch.utils import cpp_extension

            bdir = build_dir()
            bdir.mkdir(parents=True, exist_ok=True)
            name = "pano_splat_cpu_" + bdir.name.split("-")[-1]
            fresh = not any(bdir.glob("*.so"))
            if fresh:
                print(f"splatting: compiling the C++ CPU kernel once into {bdir} (about a minute)...",
                      file=sys.stderr, flush=True)
            _module = cpp_extension.load(
                name=name, sources=[str(_SRC)], extra_cflags=_CFLAGS, extra_ldflags=_LDFLAGS,
                build_directory=str(bdir), verbose=False,
            )
            if fresh:
                print("splatting: C++ kernel ready.", file=sys.stderr, flush=True)
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
