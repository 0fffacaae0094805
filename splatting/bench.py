"""``python -m splatting.bench`` (wired as ``pano-pipe bench render``).

Times the renderer on a synthetic indoor scene (Gaussians on the walls of a
6 × 4 × 3 m box around the camera, scales of a few cm), compares the direct 360°
render with the cubemap baseline, and measures how far the tangent-plane splat is
from exact ray–Gaussian evaluation as a Gaussian grows in angular size.
Writes docs/bench_render.json and docs/bench_render.md.
"""

from __future__ import annotations

import argparse
import gc
import json
import math
import os
import platform
import resource
import statistics
import sys
import time
from pathlib import Path

import torch

from .cameras import EquirectCamera
from .reference import ray_max_alpha
from .render import render
from .stitch import render_cubemap

RESOLUTIONS = ((128, 256), (256, 512), (512, 1024))
COUNTS = (20_000, 100_000, 300_000)
# the torch backend is only run where it finishes in reasonable time on a CPU
TORCH_MAX_PAIRS = 256 * 512 * 20_000


def indoor_scene(n: int, seed: int = 0, dtype=torch.float32):
    """n flat Gaussians on the walls, floor and ceiling of a 6 (x) × 3 (y) × 4 (z) m
    box; the camera (identity pose) sits 1.5 m above the floor, off-centre."""
    g = torch.Generator().manual_seed(seed)
    half = torch.tensor([3.0, 1.5, 2.0], dtype=torch.float64)
    centre = torch.tensor([0.4, 0.0, -0.3], dtype=torch.float64)  # box centre relative to the camera
    # faces: axis, sign; area weights
    faces = [(0, -1), (0, 1), (1, -1), (1, 1), (2, -1), (2, 1)]
    areas = torch.tensor([4 * half[(a + 1) % 3] * half[(a + 2) % 3] for a, _ in faces])
    face = torch.multinomial(areas / areas.sum(), n, replacement=True, generator=g)
    u = (torch.rand(n, 3, generator=g, dtype=torch.float64) * 2 - 1) * half
    axis = torch.tensor([faces[i][0] for i in range(6)])[face]
    sign = torch.tensor([faces[i][1] for i in range(6)], dtype=torch.float64)[face]
    u[torch.arange(n), axis] = sign * half[axis] + 0.01 * torch.randn(n, generator=g, dtype=torch.float64)
    means = u + centre
    # thin axis along the face normal: rotate local z onto the normal, random spin about it
    normal = torch.zeros(n, 3, dtype=torch.float64)
    normal[torch.arange(n), axis] = 1.0
    spin = torch.rand(n, generator=g, dtype=torch.float64) * 2 * math.pi
    qs = torch.stack([torch.cos(spin / 2), 0 * spin, 0 * spin, torch.sin(spin / 2)], -1)  # about z
    to_n = {0: (math.cos(math.pi / 4), 0.0, math.sin(math.pi / 4), 0.0), 1: (math.cos(math.pi / 4), -math.sin(math.pi / 4), 0.0, 0.0), 2: (1.0, 0.0, 0.0, 0.0)}
    qa = torch.tensor([to_n[int(a)] for a in range(3)], dtype=torch.float64)[axis]
    quats = _qmul(qa, qs)
    s12 = torch.exp(torch.empty(n, 2, dtype=torch.float64).uniform_(math.log(0.01), math.log(0.05), generator=g))
    scales = torch.cat([s12, torch.full((n, 1), 0.002, dtype=torch.float64)], -1)
    opac = torch.empty(n, dtype=torch.float64).uniform_(0.3, 1.0, generator=g)
    colors = torch.rand(n, 3, generator=g, dtype=torch.float64)
    return [x.to(dtype).contiguous() for x in (means, quats, scales, opac, colors)]


def _qmul(a, b):
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ], -1)


def _maxrss_mb() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return r / 1024.0 if sys.platform != "darwin" else r / 2**20


def _rss_mb() -> float:
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except OSError:
        return _maxrss_mb()


def _malloc_trim():
    try:
        import ctypes

        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


class _PeakRSS:
    """Peak resident memory above the starting level, sampled by a thread every 2 ms
    (ru_maxrss only ever grows, so it cannot see the peak of a later, smaller run)."""

    def __enter__(self):
        import threading

        gc.collect()
        _malloc_trim()  # hand freed heap back to the OS, so that new allocations show in RSS
        self.base = _rss_mb()
        self.peak = self.base
        self._stop = threading.Event()

        def poll():
            while not self._stop.is_set():
                self.peak = max(self.peak, _rss_mb())
                time.sleep(0.002)

        self._t = threading.Thread(target=poll, daemon=True)
        self._t.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._t.join()
        self.peak = max(self.peak, _rss_mb())
        self.mb = self.peak - self.base


def _count_pairs(out_backend, scene, cam, viewmat):
    """Pixel–Gaussian evaluations the tile lists imply (Σ over tile entries of the
    pixels of the Gaussian's box inside the tile) - computed from the bounding boxes."""
    from .project import project
    from .render import _color_fn

    means, quats, scales, opac, colors = scene
    with torch.no_grad():
        pr = project(means, quats, scales, opac, _color_fn(colors, None, means.shape[0]), viewmat, cam, 0.3, 0.05)
        b = pr.bbox.long()
        rows = b[:, 1] - b[:, 0] + 1
        return int((rows * b[:, 3]).sum())


def _time(fn, repeats):
    """Median wall time and median process CPU time (all threads) over ``repeats`` calls."""
    ts, cs = [], []
    for _ in range(repeats):
        _malloc_trim()
        c0, t0 = time.process_time(), time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
        cs.append(time.process_time() - c0)
    return statistics.median(ts), statistics.median(cs)


def bench_one(H, W, n, backend, repeats, seed=0):
    scene = indoor_scene(n, seed)
    cam = EquirectCamera(H, W)
    vm = torch.eye(4)

    def fwd():
        with torch.no_grad():
            return render(*scene, vm, cam, backend=backend)

    params = [x.clone().requires_grad_(True) for x in scene]

    def fwdbwd():
        out = render(*params, vm, cam, backend=backend)
        loss = out.image.sum() + 0.1 * out.depth.sum()
        loss.backward()
        for p in params:
            p.grad = None
        return out

    ran = fwd().backend  # warm-up (and the one-time compile, or the wait for another process's)
    if ran != backend:  # the kernel could not be built: do not label torch timings "cpp"
        raise RuntimeError(f"bench: backend {backend!r} requested but {ran!r} ran (see the warning above)")
    with _PeakRSS() as mf:
        t_f, c_f = _time(fwd, repeats)
    fwdbwd()
    with _PeakRSS() as mb:
        t_fb, c_fb = _time(fwdbwd, repeats)
    pairs = _count_pairs(backend, scene, cam, vm)
    return {
        "height": H, "width": W, "gaussians": n, "backend": backend,
        "forward_s": t_f, "forward_backward_s": t_fb, "forward_cpu_s": c_f, "forward_backward_cpu_s": c_fb,
        "peak_mem_forward_mb": round(mf.mb, 1), "peak_mem_forward_backward_mb": round(mb.mb, 1),
        "pairs_evaluated_bound": pairs, "pairs_per_s_forward": pairs / t_f if t_f > 0 else None,
    }


def psnr(a, b):
    mse = float(((a - b) ** 2).mean())
    return float("inf") if mse == 0 else 10 * math.log10(1.0 / mse)


def bench_cubemap(H, W, n, backend, repeats, seed=0):
    """Direct 360° render vs the cubemap baseline, timed in alternation (each pair of runs
    sees the same machine load; at least 7 pairs), with the median of the per-pair ratios."""
    scene = indoor_scene(n, seed)
    cam = EquirectCamera(H, W)
    vm = torch.eye(4)
    with torch.no_grad():
        direct = render(*scene, vm, cam, backend=backend, background=torch.zeros(3))
        cube = render_cubemap(*scene, vm, H, W, backend=backend, background=torch.zeros(3))
        td, tc, cd, cc = [], [], [], []
        for _ in range(max(repeats, 7)):
            for fn, ts, cs in ((lambda: render(*scene, vm, cam, backend=backend), td, cd),
                               (lambda: render_cubemap(*scene, vm, H, W, backend=backend), tc, cc)):
                t, c = _time(fn, 1)
                ts.append(t)
                cs.append(c)
    med = statistics.median
    return {
        "height": H, "width": W, "gaussians": n, "backend": backend, "face_size": W // 4,
        "direct_s": med(td), "cubemap_s": med(tc), "speedup": med([c / d for c, d in zip(tc, td)]),
        "direct_cpu_s": med(cd), "cubemap_cpu_s": med(cc), "pairs": len(td),
        "psnr_cubemap_vs_direct_db": psnr(cube.image.clamp(0, 1), direct.image.clamp(0, 1)),
    }


def bench_tangent_error(W=1024, angles_deg=(0.5, 1, 2, 5, 10, 20, 40)):
    """How far the tangent-plane splat is from exact ray evaluation, as a Gaussian grows.

    One Gaussian (opacity 0.99, eps2d = 0) at 2 m, latitude 30°, with angular 1σ size ``a``
    (isotropic, and 5:1 anisotropic); alpha_splat is the renderer's formula with the
    cutoff removed, alpha_exact = 0.99 · max over the ray of the 3D Gaussian. Reported:
    max and mean |Δalpha| over the pixels where either is ≥ 1/255."""
    from .project import project
    from .reference import rasterize_dense
    from .render import _color_fn

    H = W // 2
    rows = []
    cam = EquirectCamera(H, W)
    dirs = cam.pixel_dirs(torch.float64)
    for a in angles_deg:
        sig = 2.0 * math.tan(math.radians(a))
        lat = math.radians(30.0)
        d0 = torch.tensor([[0.0, -math.sin(lat), math.cos(lat)]], dtype=torch.float64)
        mean = d0 * 2.0
        quat = torch.tensor([[1.0, 0.3, -0.2, 0.1]], dtype=torch.float64)
        for aniso in (1.0, 0.2):
            scales = torch.tensor([[sig, sig * aniso, sig]], dtype=torch.float64)
            op = torch.tensor([0.99], dtype=torch.float64)
            col = torch.ones(1, 3, dtype=torch.float64)
            with torch.no_grad():
                pr = project(mean, quat, scales, op, _color_fn(col, None, 1), torch.eye(4, dtype=torch.float64),
                             cam, 0.0, 0.05)
                P = pr.packed.clone()
                P[:, 19] = float("inf")  # no cutoff: the approximation alone
                _, _, splat = rasterize_dense(P, dirs)
                exact = ray_max_alpha(mean, quat, scales, op, dirs.reshape(-1, 3))[:, 0].reshape(H, W)
            diff = (splat - exact).abs()
            mask = (splat >= 1 / 255) | (exact >= 1 / 255)
            rows.append({
                "angular_sigma_deg": a, "anisotropy": aniso,
                "max_abs_alpha_error": float(diff[mask].max()) if mask.any() else 0.0,
                "mean_abs_alpha_error_in_footprint": float(diff[mask].mean()) if mask.any() else 0.0,
                "footprint_pixels": int(mask.sum()),
            })
    return rows


def write_atomic(path, text: str) -> None:
    """Write beside ``path`` and rename over it: a concurrent reader or a second bench
    writing the same file sees one whole file, never a mix (the last writer wins)."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{time.monotonic_ns()}.tmp")
    try:
        tmp.write_text(text)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def run_render_bench(resolutions=RESOLUTIONS, counts=COUNTS, backends=("cpp", "torch"), repeats=3,
                     out_json="docs/bench_render.json", out_md="docs/bench_render.md", quick=False,
                     cubemap_cases=None, torch_max_pairs=TORCH_MAX_PAIRS, progress=True) -> dict:
    """Run the render benchmark; writes ``out_json`` and ``out_md`` (if not None) and returns the dict."""
    torch.set_num_threads(min(2, torch.get_num_threads()) if os.environ.get("PANO_BENCH_THREADS") is None
                          else int(os.environ["PANO_BENCH_THREADS"]))
    if quick:
        resolutions, counts, repeats = ((128, 256), (512, 1024)), (20_000, 100_000), min(repeats, 3)
    load = os.getloadavg() if hasattr(os, "getloadavg") else None
    result = {
        "machine": {"platform": platform.platform(), "cpus": os.cpu_count(), "torch_threads": torch.get_num_threads(),
                    "torch": torch.__version__, "loadavg_start": load},
        "scene": "Gaussians on the walls of a 6x4x3 m box around the camera, in-plane scales 1-5 cm, "
                 "0.2 cm thick, opacity U(0.3,1), RGB colours, identity pose",
        "repeats": repeats, "quick": quick, "render": [], "cubemap": [], "tangent_error": [],
    }
    log = (lambda *a: print(*a, file=sys.stderr, flush=True)) if progress else (lambda *a: None)
    for H, W in resolutions:
        for n in counts:
            for be in backends:
                if be == "torch" and H * W * n > torch_max_pairs:
                    result["render"].append({"height": H, "width": W, "gaussians": n, "backend": be, "skipped": "too slow on CPU"})
                    continue
                log(f"bench: {H}x{W} {n} gaussians, {be}")
                result["render"].append(bench_one(H, W, n, be, repeats))
    if cubemap_cases is None:
        cubemap_cases = [(H, W, 100_000) for H, W in resolutions if W >= 512] or [(resolutions[-1][0], resolutions[-1][1], counts[-1])]
    for H, W, n in cubemap_cases:
        log(f"bench: cubemap {H}x{W} {n}")
        result["cubemap"].append(bench_cubemap(H, W, n, backends[0], repeats))
    log("bench: tangent-plane error")
    result["tangent_error"] = bench_tangent_error()
    result["machine"]["loadavg_end"] = os.getloadavg() if hasattr(os, "getloadavg") else None
    _print_tables(result)
    if out_json:
        Path(out_json).parent.mkdir(parents=True, exist_ok=True)
        write_atomic(out_json, json.dumps(result, indent=2))
    if out_md:
        write_atomic(out_md, to_markdown(result))
    return result


def _fmt(x, nd=3):
    return "–" if x is None else f"{x:.{nd}f}"


def _render_rows(result):
    rows = []
    for r in result["render"]:
        if "skipped" in r:
            rows.append([f"{r['height']}×{r['width']}", f"{r['gaussians'] // 1000}k", r["backend"], "skipped: " + r["skipped"], "–", "–", "–", "–", "–", "–"])
        else:
            rows.append([f"{r['height']}×{r['width']}", f"{r['gaussians'] // 1000}k", r["backend"], _fmt(r["forward_s"]),
                         _fmt(r["forward_backward_s"]), _fmt(r.get("forward_cpu_s")), _fmt(r.get("forward_backward_cpu_s")),
                         f"{r['peak_mem_forward_mb']:.0f}",
                         f"{r['peak_mem_forward_backward_mb']:.0f}", f"{r['pairs_per_s_forward'] / 1e6:.1f}"])
    return rows


RENDER_HEAD = ["resolution", "Gaussians", "backend", "forward s", "fwd+bwd s", "forward CPU s", "fwd+bwd CPU s",
               "peak MB fwd", "peak MB fwd+bwd", "M pairs/s fwd"]
CUBE_HEAD = ["resolution", "Gaussians", "backend", "direct s", "cubemap s", "cubemap/direct", "direct CPU s",
             "cubemap CPU s", "PSNR cubemap vs direct dB"]
TAN_HEAD = ["angular σ (deg)", "anisotropy", "max abs Δalpha", "mean abs Δalpha in footprint", "footprint px"]


def _cube_rows(result):
    return [[f"{r['height']}×{r['width']}", f"{r['gaussians'] // 1000}k", r["backend"], _fmt(r["direct_s"]), _fmt(r["cubemap_s"]),
             f"{r['speedup']:.2f}×", _fmt(r.get("direct_cpu_s")), _fmt(r.get("cubemap_cpu_s")),
             f"{r['psnr_cubemap_vs_direct_db']:.2f}"] for r in result["cubemap"]]


def _tan_rows(result):
    return [[f"{r['angular_sigma_deg']:g}", f"{r['anisotropy']:g}", f"{r['max_abs_alpha_error']:.2e}",
             f"{r['mean_abs_alpha_error_in_footprint']:.2e}", str(r["footprint_pixels"])] for r in result["tangent_error"]]


def _print_tables(result):
    try:
        from rich.console import Console
        from rich.table import Table
    except ImportError:  # plain text
        for head, rows in ((RENDER_HEAD, _render_rows(result)), (CUBE_HEAD, _cube_rows(result)), (TAN_HEAD, _tan_rows(result))):
            print(" | ".join(head))
            for r in rows:
                print(" | ".join(r))
        return
    con = Console()
    for title, head, rows in (("splatting.render (equirectangular)", RENDER_HEAD, _render_rows(result)),
                              ("direct 360° vs cubemap baseline", CUBE_HEAD, _cube_rows(result)),
                              ("tangent-plane splat vs exact ray evaluation", TAN_HEAD, _tan_rows(result))):
        t = Table(title=title)
        for h in head:
            t.add_column(h)
        for r in rows:
            t.add_row(*r)
        con.print(t)


def _cube_pairs(result) -> str:
    return str(max((c.get("pairs", result["repeats"]) for c in result["cubemap"]), default=0))


def _md_table(head, rows):
    out = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    out += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(out)


def _targets(result) -> str:
    """The issue's targets, checked against this run."""
    lines = []
    r = [x for x in result["render"] if x.get("backend") == "cpp" and x["height"] == 512 and x["gaussians"] == 100_000
         and "skipped" not in x]
    if r:
        r = r[0]
        f, fb = r["forward_s"], r["forward_backward_s"]
        lines.append(f"- 512×1024, 100k Gaussians, `cpp`: forward {f:.3f} s (target ≤ 0.2 s: "
                     f"{'met' if f <= 0.2 else 'not met'}), forward+backward {fb:.3f} s (target ≤ 0.5 s: "
                     f"{'met' if fb <= 0.5 else 'not met'}).")
    for c in result["cubemap"]:
        lines.append(f"- {c['height']}×{c['width']}, {c['gaussians'] // 1000}k: direct 360° is {c['speedup']:.2f}× faster "
                     f"than the cubemap baseline (target ≥ 2×: {'met' if c['speedup'] >= 2 else 'not met'}).")
    m = result["machine"]
    load = (m.get("loadavg_start") or [0])[0]
    if load and m.get("cpus") and load > 0.75 * m["cpus"]:
        lines.append(f"- This run was taken **under load** (load average {load:.1f} on {m['cpus']} CPUs, other jobs "
                     "running): wall times are pessimistic; where \"CPU s\" ≈ wall time the renderer effectively "
                     "had one core, and the targets assume an otherwise idle machine.")
    return "\n".join(lines) if lines else "- (the 512×1024 / 100k case was not in this run)"


def to_markdown(result) -> str:
    m = result["machine"]
    return f"""# Render benchmark

Generated by `pano-pipe bench render` (`python -m splatting.bench`{' --quick' if result['quick'] else ''}).
GPU figures (the `cuda` backend): `pano-pipe bench render --device cuda`, written by `make gpu-check`
to docs/gpu_check/bench_render_gpu.md (docs/gpu.md).
Machine: {m['platform']}, {m['cpus']} CPUs, torch {m['torch']} with {m['torch_threads']} threads;
load average at start {m['loadavg_start']}, at end {m.get('loadavg_end')}
(the machine is shared: figures taken under a load above the core count are pessimistic).

Scene: {result['scene']}. Median of {result['repeats']} runs after one warm-up.
"s" columns are wall-clock medians; "CPU s" is the median process CPU time of the same runs
(all threads; on a loaded machine the wall time exceeds CPU time / threads).
Peak memory is the rise of the process's resident set size (RSS, /proc/self/statm sampled
every 2 ms, after `malloc_trim`) above its level before the timed runs; tracemalloc cannot
see torch's allocations. It covers the renderer's working memory (outputs, tile lists,
per-thread gradient buffers), not the scene itself.
"pairs" counts the pixel–Gaussian evaluations implied by the Gaussians' pixel boxes (an upper
bound on the work; pixels that saturated early are skipped).

## Targets of the issue

{_targets(result)}

## Forward and forward+backward

{_md_table(RENDER_HEAD, _render_rows(result))}

## Direct 360° rendering vs the cubemap baseline

Same scene; the cubemap renders six 90° faces of W/4 pixels (each a full `render` call:
projection, sort, binning and rasterisation of all Gaussians for that face) and resamples
them bilinearly into the H×W panorama in one gather pass. The two are timed in alternation
({_cube_pairs(result)} pairs, so both see the same machine load); "cubemap/direct" is the median
of the per-pair ratios.

{_md_table(CUBE_HEAD, _cube_rows(result))}

## Tangent-plane approximation vs exact ray–Gaussian evaluation

One Gaussian (opacity 0.99, `eps2d=0`) 2 m away at latitude 30°, 512×1024, isotropic and
5:1 anisotropic. "exact" is 0.99 × the maximum of the 3D Gaussian along each pixel ray; the
splat is the renderer's formula without its 3σ / 1/255 cutoff, so only the tangent-plane
approximation is measured. Errors are over the pixels where either value is ≥ 1/255.
Up to a few degrees (a Gaussian spanning ~10–40 pixels at this resolution) the error stays
around 10⁻³; it grows roughly with the square of the angular size. From 20° the 3D Gaussian
(σ ≈ 0.7 m at 2 m) is still above 1/255 on rays pointing away from it (the footprint is the
whole sphere), which no splat on a tangent plane can render.

{_md_table(TAN_HEAD, _tan_rows(result))}
"""


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m splatting.bench", description=__doc__.split("\n")[0])
    ap.add_argument("--resolutions", default=",".join(f"{h}x{w}" for h, w in RESOLUTIONS), help="e.g. 128x256,512x1024")
    ap.add_argument("--counts", default=",".join(str(c) for c in COUNTS), help="e.g. 20000,100000")
    ap.add_argument("--backends", default="cpp,torch")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out-json", default="docs/bench_render.json")
    ap.add_argument("--out-md", default="docs/bench_render.md")
    ap.add_argument("--quick", action="store_true", help="a small grid (128x256 and 512x1024; 20k and 100k)")
    ap.add_argument("--markdown-from-json", metavar="JSON", help="only rewrite --out-md from an earlier JSON result")
    a = ap.parse_args(argv)
    if a.markdown_from_json:
        write_atomic(a.out_md, to_markdown(json.loads(Path(a.markdown_from_json).read_text())))
        return
    res = tuple(tuple(int(v) for v in r.split("x")) for r in a.resolutions.split(","))
    counts = tuple(int(c) for c in a.counts.split(","))
    run_render_bench(res, counts, tuple(a.backends.split(",")), a.repeats, a.out_json, a.out_md, quick=a.quick)


if __name__ == "__main__":
    main()
