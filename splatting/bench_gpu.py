"""``pano-pipe bench render --device cuda``: the splatting backends on a GPU.

For each resolution and Gaussian count: forward and forward+backward time (CUDA events,
median of ``repeats`` after a warm-up that includes Triton's compile), FPS, and peak GPU
memory (``torch.cuda.max_memory_allocated``), for the ``cuda`` (Triton) and ``torch``
backends on the same GPU; then direct 360° against the cubemap baseline. Same scene as
the CPU bench (:func:`splatting.bench.indoor_scene`). Writes bench_render_gpu.{json,md}.
"""

from __future__ import annotations

import json
import statistics
from pathlib import Path

import torch

from .bench import indoor_scene, psnr, write_atomic
from .cameras import EquirectCamera
from .render import DEFAULT_TILE, render
from .stitch import render_cubemap

RESOLUTIONS = ((512, 1024), (1024, 2048))
COUNTS = (100_000, 300_000, 1_000_000)
#: torch backend cases above this many pixel × Gaussian products are skipped (minutes per render)
TORCH_MAX_PRODUCT = 512 * 1024 * 300_000


def no_cuda_reason() -> str | None:
    """Why this machine cannot run the GPU bench (one line), or None."""
    if not torch.cuda.is_available():
        return "torch sees no CUDA device here (the GPU bench needs one; run it on a GPU machine, docs/gpu.md)"
    return None


def _cuda_time(fn, repeats):
    """Median device time (s) of ``fn`` over ``repeats`` calls, measured with CUDA events."""
    times = []
    for _ in range(repeats):
        start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        start.record()
        fn()
        end.record()
        end.synchronize()
        times.append(start.elapsed_time(end) / 1000.0)
    return statistics.median(times)


def _peak_mb(fn):
    torch.cuda.synchronize()
    torch.cuda.reset_peak_memory_stats()
    base = torch.cuda.memory_allocated()
    fn()
    torch.cuda.synchronize()
    return (torch.cuda.max_memory_allocated() - base) / 2**20


def walked_pairs(scene, cam, viewmat, tile_size):
    """(pairs of the splats' pixel boxes, pairs the ``cuda`` rasteriser walks after the tile test)."""
    from .bin_triton import PairCapacity, bin_gaussians
    from .project_triton import project_gaussians
    from .render import DEFAULT_EPS2D, _color_fn

    with torch.no_grad():  # as render() with its defaults, which bench_one times
        packed, ints, _, _ = project_gaussians(*scene, viewmat, cam, DEFAULT_EPS2D, 0.05, None, tile_size, _color_fn)
        toff, _, total = bin_gaussians(ints, cam.height, cam.width, tile_size, capacity=PairCapacity(initial=1 << 20),
                                       packed=packed, camera=cam)
    return int(total), int(toff[-1])


def bench_one(H, W, n, backend, repeats, seed=0, tile_size=DEFAULT_TILE):
    scene = [x.cuda() for x in indoor_scene(n, seed)]
    cam = EquirectCamera(H, W)
    vm = torch.eye(4, device="cuda")
    params = [x.clone().requires_grad_(True) for x in scene]

    def fwd():
        with torch.no_grad():
            return render(*scene, vm, cam, backend=backend, tile_size=tile_size)

    def fwdbwd():
        out = render(*params, vm, cam, backend=backend, tile_size=tile_size)
        (out.image.sum() + 0.1 * out.depth.sum()).backward()
        for p in params:
            p.grad = None

    ran = fwd().backend  # warm-up: Triton compiles the kernels on first use
    if ran != backend:
        raise RuntimeError(f"bench: backend {backend!r} requested but {ran!r} ran (see the warning above)")
    fwdbwd()
    t_f = _cuda_time(fwd, repeats)
    t_fb = _cuda_time(fwdbwd, repeats)
    box, walked = walked_pairs(scene, cam, vm, tile_size) if backend == "cuda" else (None, None)
    return {"height": H, "width": W, "gaussians": n, "backend": backend, "tile_size": tile_size,
            "box_pairs": box, "walked_pairs": walked, "forward_s": t_f,
            "forward_backward_s": t_fb, "fps": 1.0 / t_f if t_f > 0 else None,
            "peak_mem_forward_mb": round(_peak_mb(fwd), 1), "peak_mem_forward_backward_mb": round(_peak_mb(fwdbwd), 1)}


def bench_cubemap(H, W, n, repeats, seed=0):
    scene = [x.cuda() for x in indoor_scene(n, seed)]
    cam = EquirectCamera(H, W)
    vm = torch.eye(4, device="cuda")
    bg = torch.zeros(3, device="cuda")
    with torch.no_grad():
        direct = render(*scene, vm, cam, background=bg)
        cube = render_cubemap(*scene, vm, H, W, background=bg)
        t_d = _cuda_time(lambda: render(*scene, vm, cam), repeats)
        t_c = _cuda_time(lambda: render_cubemap(*scene, vm, H, W), repeats)
    return {"height": H, "width": W, "gaussians": n, "backend": direct.backend, "face_size": W // 4,
            "direct_s": t_d, "cubemap_s": t_c, "speedup": t_c / t_d if t_d > 0 else None,
            "psnr_cubemap_vs_direct_db": psnr(cube.image.clamp(0, 1).cpu(), direct.image.clamp(0, 1).cpu())}


def run_gpu_render_bench(resolutions=RESOLUTIONS, counts=COUNTS, backends=("cuda", "torch"), repeats=10,
                         out_json="docs/bench_render_gpu.json", out_md="docs/bench_render_gpu.md", log=print,
                         tile_sizes=(DEFAULT_TILE,)) -> dict:
    """The table above; `tile_sizes`: the ``cuda`` backend's rows for each (the torch reference's
    speed does not depend on it: it runs at the default only)."""
    result = {"machine": {"gpu": torch.cuda.get_device_name(), "torch": torch.__version__,
                          "cuda": torch.version.cuda},
              "repeats": repeats, "render": [], "cubemap": []}
    try:
        import triton

        result["machine"]["triton"] = triton.__version__
    except ImportError:
        result["machine"]["triton"] = None
    for H, W in resolutions:
        for n in counts:
            for be in backends:
                if be == "torch" and H * W * n > TORCH_MAX_PRODUCT:
                    result["render"].append({"height": H, "width": W, "gaussians": n, "backend": be,
                                             "skipped": "torch reference: too slow at this size"})
                    continue
                for ts in tile_sizes if be == "cuda" else (DEFAULT_TILE,):
                    log(f"bench (GPU): {H}x{W} {n} gaussians, {be}, {ts}x{ts} tiles")
                    result["render"].append(bench_one(H, W, n, be, repeats, tile_size=ts))
    for H, W in resolutions:
        log(f"bench (GPU): cubemap {H}x{W} 300000")
        result["cubemap"].append(bench_cubemap(H, W, 300_000, repeats))
    for path, text in ((out_json, json.dumps(result, indent=2)), (out_md, to_markdown(result))):
        if path:
            Path(path).parent.mkdir(parents=True, exist_ok=True)
            write_atomic(path, text)
    return result


def _ms(x):
    return "–" if x is None else f"{1000 * x:.2f}"


def to_markdown(result) -> str:
    m = result["machine"]
    rows = []
    for r in result["render"]:
        if "skipped" in r:
            rows.append(f"| {r['height']}×{r['width']} | {r['gaussians']:,} | {r['backend']} | – | – | – | – | – | – | "
                        f"{r['skipped']} |")
            continue
        tile = r.get("tile_size", DEFAULT_TILE)  # results written before these columns
        walked = "–" if r.get("walked_pairs") is None else f"{r['walked_pairs']:,} / {r['box_pairs']:,}"
        rows.append(f"| {r['height']}×{r['width']} | {r['gaussians']:,} | {r['backend']} | {tile} | {walked} | "
                    f"{_ms(r['forward_s'])} | "
                    f"{_ms(r['forward_backward_s'])} | {r['fps']:.0f} | {r['peak_mem_forward_mb']:.0f} / "
                    f"{r['peak_mem_forward_backward_mb']:.0f} | |")
    cube = [f"| {c['height']}×{c['width']} | {c['gaussians']:,} | {c['backend']} | {_ms(c['direct_s'])} | "
            f"{_ms(c['cubemap_s'])} | {c['speedup']:.2f} | {c['psnr_cubemap_vs_direct_db']:.1f} |"
            for c in result["cubemap"]]
    return f"""# Render benchmark on a GPU

Generated by `pano-pipe bench render --device cuda` on **{m['gpu']}** (torch {m['torch']}, CUDA {m['cuda']},
Triton {m['triton']}); median of {result['repeats']} runs timed with CUDA events after a warm-up. Scene as in
docs/bench_render.md (Gaussians on the walls of a box around the camera). Peak memory: GPU memory
allocated during the call above what was allocated before it (forward / forward+backward). Pairs: the
(tile, Gaussian) pairs the rasteriser walks after the tile test, of those the splats' pixel boxes cover.

| resolution | Gaussians | backend | tile | pairs walked / in the boxes | forward ms | fwd+bwd ms | FPS | peak MiB | note |
|---|---|---|---|---|---|---|---|---|---|
{chr(10).join(rows)}

Direct 360° against the cubemap baseline (six 90° faces of W/4, resampled), default backend:

| resolution | Gaussians | backend | direct ms | cubemap ms | cubemap / direct | PSNR cubemap vs direct (dB) |
|---|---|---|---|---|---|---|
{chr(10).join(cube)}
"""
