"""Ahead-of-time compile check of the ``cuda`` backend's Triton kernels, no GPU needed.

Each kernel is compiled with ``triton.compile`` for an NVIDIA target (sm_80, sm_90) at the
signature a real launch binds: the launch is spelled out once in splatting/raster_triton.py
(``forward_launch`` / ``backward_launch``) and bound here by the backend's own argument
binder, with aligned mock tensors, so pointer alignment, integer divisibility and the
constexprs are those of a 512×1024 render. ``ptxas -v`` (bundled in the triton wheel)
reports registers and spill bytes; ``cuobjdump -sass`` disassembles the cubin, and the
instructions of each kernel's inner loop (the body of its hot backward branch) are counted:
divided by the Gaussian–pixel pairs one trip of the loop evaluates per thread, that is the
"SASS instructions per pair" of docs/gpu.md.

Triton must not be in interpreter mode here (``TRITON_INTERPRET`` unset when triton is first
imported); :func:`report_in_subprocess` runs :func:`report` in a fresh interpreter, which is
how the test suite (interpreter on) checks the compiled kernels.

    pano-pipe bench kernels [--out DIR] [--doc docs/gpu.md]   (or python -m splatting.kernel_report)
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import re
import subprocess
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

ARCHS = (80, 90)
RENDER_HW = (512, 1024)
TILE = 16


@dataclass
class KernelStats:
    kernel: str
    arch: int
    dtype: str
    num_warps: int
    registers: int
    spill_stores: int  # bytes
    spill_loads: int  # bytes
    shared: int  # bytes of shared memory (static + what triton asks at launch)
    loop_instructions: int  # SASS instructions in the inner loop body
    pairs_per_trip: float  # Gaussian–pixel pairs one trip evaluates per thread
    barriers: int  # BAR instructions in the inner loop
    shuffles: int  # SHFL instructions in the inner loop
    approximate_divisions: int = 0  # float32 `/` in the PTX as div.full/div.approx (2 ulp), not torch's div.rn

    @property
    def per_pair(self) -> float:
        return self.loop_instructions / self.pairs_per_trip if self.pairs_per_trip else float("nan")


def _cuobjdump() -> str:
    """The cuobjdump shipped in the triton wheel, else the one on PATH (a CUDA toolkit)."""
    import shutil

    import triton

    bundled = Path(triton.__file__).parent / "backends" / "nvidia" / "bin" / "cuobjdump"
    found = str(bundled) if bundled.exists() else shutil.which("cuobjdump")
    if not found:
        raise RuntimeError("cuobjdump not found (neither in the triton wheel nor on PATH)")
    return found


def bind(fn, args, options, backend=None):
    """(bound arguments, specialisation key, options) of ``fn[grid](*args, **options)``, as
    Triton's own launcher binds them for `backend` (default: sm_90's, no GPU needed)."""
    from triton.backends.compiler import GPUTarget
    from triton.compiler import make_backend
    from triton.runtime.jit import create_function_from_signature

    backend = backend or make_backend(GPUTarget("cuda", ARCHS[-1], 32))
    return create_function_from_signature(fn.signature, fn.params, backend)(*args, **options)


def _compile(fn, args, options, arch):
    """Compile ``fn`` as ``fn[grid](*args, **options)`` would for ``sm_<arch>``; returns
    (compiled kernel, ptxas log)."""
    import triton
    from triton import knobs
    from triton.backends.compiler import GPUTarget
    from triton.compiler import ASTSource, make_backend

    target = GPUTarget("cuda", arch, 32)
    backend = make_backend(target)
    bound, spec, opts = bind(fn, args, options, backend)
    opts, signature, constexprs, attrs = fn._pack_args(backend, dict(options), bound, spec, opts)
    log = io.StringIO()
    # ptxas prints its -v report only when it runs: bypass triton's cache
    with knobs.nvidia.scope(), knobs.compilation.scope(), contextlib.redirect_stdout(log):
        knobs.nvidia.dump_ptxas_log = True
        knobs.compilation.always_compile = True
        compiled = triton.compile(ASTSource(fn, signature, constexprs, attrs), target=target, options=opts.__dict__)
    return compiled, log.getvalue()


def _ptxas_numbers(log: str):
    regs = int(re.search(r"Used (\d+) registers", log).group(1))
    spill = re.search(r"(\d+) bytes spill stores, (\d+) bytes spill loads", log)
    return regs, int(spill.group(1)), int(spill.group(2))


_SASS_LINE = re.compile(r"/\*([0-9a-f]{4,})\*/\s+(.*?);")


def sass_instructions(cubin: bytes) -> list[tuple[int, str]]:
    """(address, instruction text) of every SASS instruction in the cubin."""
    import tempfile

    with tempfile.NamedTemporaryFile(suffix=".cubin") as f:
        f.write(cubin)
        f.flush()
        out = subprocess.run([_cuobjdump(), "-sass", f.name], capture_output=True, text=True,
                             check=True).stdout
    return [(int(m.group(1), 16), m.group(2).strip()) for m in map(_SASS_LINE.search, out.splitlines()) if m]


def inner_loop(instrs):
    """The hottest loop: the backward branch (a BRA to a lower address) with the smallest body
    that still holds floating-point work (MUFU, the exp/reciprocal unit) — for the kernels here
    the per-Gaussian loop. Returns the instructions of its body."""
    addr = [a for a, _ in instrs]
    loops = []
    for i, (a, text) in enumerate(instrs):
        m = re.search(r"\bBRA\b.*?(0x[0-9a-f]+)\s*$", text)
        if m and int(m.group(1), 16) < a:
            j = addr.index(int(m.group(1), 16))
            body = [t for _, t in instrs[j:i + 1]]
            if any(t.split()[0].startswith("MUFU") or " MUFU" in t for t in body):
                loops.append(body)
    if not loops:
        return []
    return min(loops, key=len)


def _mock_launches(dtype_name: str, H: int, W: int, ts: int, N: int = 300_000):
    """Every kernel launch of a render and its backward, with mock tensors (no memory):
    (name, (kernel, grid, args, options), Gaussian-pixel pairs per inner-loop trip or None)."""
    import torch
    from triton.runtime.jit import MockTensor

    from . import bin_triton, project_triton, project_triton_backward
    from . import raster_triton as rt

    class Mock(MockTensor):  # a 16-byte aligned tensor of ``dtype``, as torch allocates them
        def element_size(self):
            return self.dtype.itemsize

    f = Mock(getattr(torch, dtype_name))
    i32 = Mock(torch.int32)
    i64 = Mock(torch.int64)
    b = Mock(torch.bool)
    size = f.element_size()
    # training's forward and backward (over a background; a photometric loss: the colour's gradient
    # alone), and the backward with depth and alpha
    out = [("forward", rt.forward_launch(f, f, i32, i32, f, f, f, i32, H, W, ts, f),
            rt.pairs_per_trip("forward", ts, size)),
           ("backward", rt.backward_launch(f, f, i32, i32, f, i32, f, None, None, f, H, W, ts, f),
            rt.pairs_per_trip("backward", ts, size)),
           ("backward + depth, alpha", rt.backward_launch(f, f, i32, i32, f, i32, f, f, f, f, H, W, ts),
            rt.pairs_per_trip("backward", ts, size))]
    for sh in (-1, 3):
        launch = project_triton.projection_launch(
            Mock(f.dtype, [N, 3]), f, f, f, f, f, f, f, i32, b, f, H, W, ts, True, sh, 16 if sh >= 0 else 1)
        out.append((f"project ({'RGB' if sh < 0 else 'SH 3'})", launch, None))
        # what training runs (no view-matrix gradient); float64's is checked against it in the tests
        if dtype_name == "float32":
            launch = project_triton_backward.backward_launch(
                Mock(f.dtype, [N, 3]), f, f, f, f, f, b, f, (f, f, f, f, f, f, None), True, sh, 16 if sh >= 0 else 1)
            out.append((f"project backward ({'RGB' if sh < 0 else 'SH 3'})", launch, None))
    if dtype_name == "float32":  # the training loss (splatting/photometric_triton.py), masked and weighted
        from . import photometric_triton as pt

        img, plane = Mock(f.dtype, [H, W, 3]), Mock(f.dtype, [H, W])
        sp = (3 * W, 3, 1)
        fwd = pt._launches(img, img, plane, plane, f, f, f, f, f, (0.8, 0.2), H, W, sp, sp)
        bwd = pt._backward_launches(f, f, img, img, plane, plane, f, f, (f, None, None), img, (0.8, 0.2), H, W,
                                    sp, sp, sp)
        names = ("loss: moments", "loss: SSIM", "loss: sum", "loss backward: blur", "loss backward: combine")
        out.extend((name, launch, None) for name, launch in zip(names, fwd + bwd))
        from . import turn_triton  # the random turn of a training panorama (bicubic)

        out.append(("random turn", turn_triton.turn_launch(img, f, f, img, H, W, 3, True, True), None))
        from . import densify_triton  # a view's densification statistics

        u8 = Mock(torch.uint8)
        out.append(("densify statistics", densify_triton.add_launch(f, u8, i32, f, f, f, N, 2, 1, 6, 81.5, 163.0),
                    None))
        from . import layout_triton  # L_layout's value and gradient

        out.append(("layout loss", layout_triton.layout_launch(f, i64, f, f, f, f, N, 3, f), None))
        from . import adam_triton  # the optimiser's step over every parameter

        params = [Mock(f.dtype, [N, c]) for c in (3, 4, 3, 1, 3, 45)]
        out.append(("adam", adam_triton.adam_launch([(p, p, p, p, 1e-3) for p in params], 10, (0.9, 0.999), 1e-15, f),
                    None))
    # the pair writer with its tile test, in the render's dtype
    out.append(("emit pairs", bin_triton.emit_launch(i32, i64, i32, i32, i32, 1 << 22, ts, W // ts, N, f, (f, f)), None))
    return out


def report(archs=ARCHS, dtypes=("float32", "float64"), H=RENDER_HW[0], W=RENDER_HW[1], ts=TILE) -> list[KernelStats]:
    if os.environ.get("TRITON_INTERPRET", "0") not in ("", "0"):
        raise RuntimeError("the compile check needs TRITON_INTERPRET unset; use report_in_subprocess()")
    rows = []
    for dtype in dtypes:
        for name, (fn, _grid, args, options), pairs in _mock_launches(dtype, H, W, ts):
            for arch in archs:
                compiled, log = _compile(fn, args, options, arch)
                regs, st, ld = _ptxas_numbers(log)
                body = inner_loop(sass_instructions(compiled.asm["cubin"])) if pairs else []
                rows.append(KernelStats(
                    kernel=name, arch=arch, dtype=dtype, num_warps=options["num_warps"], registers=regs,
                    spill_stores=st, spill_loads=ld, shared=int(compiled.metadata.shared),
                    loop_instructions=len(body), pairs_per_trip=pairs or 0.0,
                    barriers=sum(t.split()[0].startswith("BAR") for t in body),
                    shuffles=sum("SHFL" in t for t in body),
                    approximate_divisions=len(re.findall(r"\bdiv\.(?:full|approx)\.", compiled.asm["ptx"]))))
    return rows


def variants(sizes, dtype_name: str = "float32", H: int = RENDER_HW[0], W: int = RENDER_HW[1],
             ts: int = TILE) -> dict[str, int]:
    """How many compiled variants of each kernel a training run needs whose Gaussian count takes
    each of `sizes`: Triton compiles one per specialisation key of a launch's arguments (each
    integer's `% 16` and `== 1`, each pointer's alignment), so an argument that changed its key
    with every densification would compile the kernel anew at each (seconds: the projection's
    gradient takes 8 s to compile). Needs TRITON_INTERPRET unset, no GPU."""
    keys: dict[str, set] = {}
    for n in sizes:
        for name, (fn, _grid, args, options), _ in _mock_launches(dtype_name, H, W, ts, N=int(n)):
            keys.setdefault(name, set()).add(repr(bind(fn, args, options)[1]))
    return {name: len(k) for name, k in keys.items()}


def loaded_variants() -> dict[str, int]:
    """Variants of each of the package's Triton kernels this process has compiled or loaded from
    Triton's disk cache so far (``module.kernel`` → count; kernels not launched are left out),
    read from Triton's in-memory caches: a GPU run's figure to set beside :func:`variants`."""
    import importlib
    import pkgutil

    from triton.runtime.jit import JITFunction

    from . import __path__ as package_path

    counts = {}
    for module in pkgutil.iter_modules(package_path):
        if not module.name.endswith(("_triton", "_triton_backward")):
            continue
        for name, fn in vars(importlib.import_module(f"{__package__}.{module.name}")).items():
            if isinstance(fn, JITFunction):
                n = sum(len(cache[0]) for cache in fn.device_caches.values())
                if n:
                    counts[f"{module.name}.{name}"] = n
    return counts


def _compiled_python(code: str) -> subprocess.Popen:
    """`python -c code` in a fresh Python whose triton is not in interpreter mode (the compile
    checks', from a test process that runs the kernels in the interpreter), this checkout first on
    its path; stdout and stderr piped as text."""
    env = {k: v for k, v in os.environ.items() if k != "TRITON_INTERPRET"}
    root = Path(__file__).resolve().parents[1]
    env["PYTHONPATH"] = os.pathsep.join([str(root)] + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])
    return subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=env, cwd=root)


def last_line_compiled(code: str) -> str:
    """The last line `code` prints, run by :func:`_compiled_python`; its stderr's end on failure."""
    proc = _compiled_python(code)
    out, err = proc.communicate()
    if proc.returncode != 0 or not out.strip():
        raise RuntimeError(f"compiled-mode python failed:\n{err[-4000:]}")
    return out.strip().splitlines()[-1]


def report_in_subprocess(archs=ARCHS, **kw) -> list[KernelStats]:
    """:func:`report` in fresh Pythons whose triton is not in interpreter mode, one per target
    architecture, run side by side (ptxas is single-threaded)."""
    procs = []
    for arch in archs:
        code = ("import json; from dataclasses import asdict; from splatting.kernel_report import report; "
                f"print(json.dumps([asdict(r) for r in report(archs=({arch},), **{kw!r})]))")
        procs.append(_compiled_python(code))
    rows = []
    for proc in procs:
        out, err = proc.communicate()
        if proc.returncode != 0:
            raise RuntimeError(f"compile check failed:\n{err[-4000:]}")
        rows += [KernelStats(**r) for r in json.loads(out.strip().splitlines()[-1])]
    order = {"float32": 0, "float64": 1}
    kernels = ["forward", "backward", "project (RGB)", "project (SH 3)", "emit pairs"]
    return sorted(rows, key=lambda r: (order.get(r.dtype, 2), kernels.index(r.kernel) if r.kernel in kernels else 99,
                                       r.arch))


def to_markdown(rows) -> str:
    lines = ["| kernel | dtype | sm | warps | registers | spill st/ld (B) | shared (B) | loop SASS | pairs/trip "
             "| SASS per pair | BAR in loop | SHFL in loop |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        loop = (f"{r.loop_instructions} | {r.pairs_per_trip:g} | {r.per_pair:.1f} | {r.barriers} | {r.shuffles}"
                if r.pairs_per_trip else "– | – | – | – | –")
        lines.append(f"| {r.kernel} | {r.dtype} | {r.arch} | {r.num_warps} | {r.registers} | {r.spill_stores}/"
                     f"{r.spill_loads} | {r.shared} | {loop} |")
    return "\n".join(lines) + "\n"


MARK_BEGIN = "<!-- kernel-table: pano-pipe bench kernels --doc docs/gpu.md -->"
MARK_END = "<!-- /kernel-table -->"


def write(rows, out_md: Path, out_json: Path, doc: Path | None = None):
    """The table to ``out_md``/``out_json`` (and between the markers of ``doc``); prints it."""
    table = to_markdown(rows)
    print(table)
    out_md.parent.mkdir(parents=True, exist_ok=True)
    out_md.write_text(f"# Triton kernels compiled ahead of time ({RENDER_HW[0]}x{RENDER_HW[1]} launches)\n\n{table}")
    out_json.write_text(json.dumps([asdict(r) | {"per_pair": r.per_pair} for r in rows], indent=2) + "\n")
    if doc is not None:
        text = doc.read_text()
        if MARK_BEGIN not in text or MARK_END not in text:
            raise ValueError(f"{doc}: no {MARK_BEGIN!r} ... {MARK_END!r} section")
        head, rest = text.split(MARK_BEGIN, 1)
        _, tail = rest.split(MARK_END, 1)
        doc.write_text(f"{head}{MARK_BEGIN}\n{table}{MARK_END}{tail}")


def main(argv=None):
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=Path("runs/bench"))
    ap.add_argument("--doc", type=Path, default=None)
    args = ap.parse_args(argv)
    write(report(), args.out / "bench_kernels.md", args.out / "bench_kernels.json", args.doc)


if __name__ == "__main__":
    main()
