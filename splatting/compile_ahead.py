"""Compile the projection's later SH-degree variants in a background thread while training runs.

Training raises the SH degree every ``sh_degree_every`` iterations (0 → 3), and each degree is
a variant of the projection's forward and backward kernels (their ``SH_DEGREE`` constexpr),
compiled where it is first launched. On the H200's first run that stopped training for seconds
at each raise (the SH 3 backward alone compiles in ~8 s): 70, 53 and 42 it/s over the first
3,000 iterations against 170 after (docs/gpu.md). Triton leaves the GIL free while it compiles
(a Python thread kept its pace beside a 16 s compile, docs/gpu.md), so the compiles can run
beside training instead.

:func:`sh_degrees` names the degrees a run will reach. The first launch of each projection kernel
then also starts a thread that compiles its other degrees with Triton's ``warmup`` (compile and
cache, no launch) on the launch's own arguments with ``SH_DEGREE`` replaced: the later launch
computes the same specialisation key and finds the kernel in Triton's cache. Lowest degree
first, once per kernel and key; a failure only warns (the launch would compile it then). Nothing
happens in the Triton interpreter, where there is nothing to compile.
"""

from __future__ import annotations

import threading
import warnings

import torch

_wanted: tuple[int, ...] = ()
_started: set = set()
_threads: list[threading.Thread] = []
_lock = threading.Lock()


def sh_degrees(*degrees: int) -> None:
    """Compile the projection's variants for these SH degrees ahead (none: stop doing so)."""
    global _wanted
    _wanted = tuple(sorted({int(d) for d in degrees}))


def launch(kernel, grid, args, options: dict) -> None:
    """``kernel[grid](*args, **options)``, and the first time this kernel runs with these options
    (``SH_DEGREE`` aside) the wanted degrees' variants compiled in a background thread."""
    kernel[grid](*args, **options)
    if not _wanted or options.get("SH_DEGREE", -1) < 0 or not hasattr(kernel, "warmup") or _interpreted(kernel):
        return  # nothing asked, RGB colours (no SH variants), or nothing to compile
    rest = tuple(sorted((k, v) for k, v in options.items() if k != "SH_DEGREE"))
    todo = []
    with _lock:
        for d in _wanted:
            key = (kernel, d, rest, tuple(getattr(a, "dtype", None) for a in args))
            if d != options["SH_DEGREE"] and (d + 1) ** 2 <= options.get("K", 0) and key not in _started:
                _started.add(key)
                todo.append(d)
    if todo:
        device = next((a.device for a in args if isinstance(a, torch.Tensor)), None)
        thread = threading.Thread(target=_compile, args=(kernel, grid, args, options, todo, device), daemon=True,
                                  name="pano-pipe-compile-ahead")
        thread.start()
        _threads.append(thread)


def wait(timeout: float | None = None) -> None:
    """Wait for the compiles started so far (benchmarks and tests)."""
    for thread in list(_threads):
        thread.join(timeout)
    _threads[:] = [t for t in _threads if t.is_alive()]


def _compile(kernel, grid, args, options, degrees, device):
    try:
        if device is not None and device.type == "cuda":
            torch.cuda.set_device(device)  # the thread's current device is the first GPU otherwise
        for d in degrees:
            kernel.warmup(*args, grid=grid, **{**options, "SH_DEGREE": d})
    except Exception as exc:  # the launch compiles it itself then: slower, not wrong
        warnings.warn(f"splatting: compiling SH degrees {degrees} ahead failed ({type(exc).__name__}: {exc}); "
                      "each compiles at its first launch instead", RuntimeWarning, stacklevel=1)


def _interpreted(kernel) -> bool:
    try:
        from triton.runtime.interpreter import InterpretedFunction
    except ImportError:
        return False
    return isinstance(kernel, InterpretedFunction)
