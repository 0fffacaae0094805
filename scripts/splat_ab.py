"""The fused CPU kernel of this checkout against another checkout's, in one process, on the
same inputs, alternating call by call (so both see the same load), with the median of the
per-pair ratios:

    PYTHONPATH=$PWD python scripts/splat_ab.py --base /tmp/base                # wall clock
    PYTHONPATH=$PWD python scripts/splat_ab.py --base /tmp/base --threads 1    # CPU time of one thread
    PYTHONPATH=$PWD python scripts/splat_ab.py --base /tmp/base --state s.pt   # a saved training state

Both kernels are built and loaded side by side (each build folder is keyed by its sources,
docs/splatting.md). Times the kernel calls themselves (projection, sort, binning and
rasterisation forward; rasterisation and projection backward), with the same upstream
gradients, and checks first that both give the same image and gradients.
`--state` is a `torch.save`d dict {"args": [means, quats, scales, opacities, rgb],
"viewmat": [4,4]} (e.g. a trainer's Gaussians); default: the benchmark room (splatting.bench).
"""

from __future__ import annotations

import argparse
import importlib.util
import statistics
import time
from pathlib import Path

import torch

from splatting import EquirectCamera
from splatting import raster_cpp
from splatting.bench import indoor_scene


def _load_other(checkout: Path):
    spec = importlib.util.spec_from_file_location("raster_cpp_other", checkout / "splatting" / "raster_cpp.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.load()


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--base", type=Path, required=True, help="the other checkout (e.g. a git worktree)")
    ap.add_argument("--height", type=int, default=512)
    ap.add_argument("--gaussians", type=int, default=100_000)
    ap.add_argument("--state", type=Path, default=None, help="Gaussians saved with torch.save (see above)")
    ap.add_argument("--rounds", type=int, default=10)
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0 = torch's default)")
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    mods = {"base": _load_other(args.base.resolve()), "this": raster_cpp.load()}
    H, W = args.height, 2 * args.height
    if args.state is None:
        means, quats, scales, opac, rgb = indoor_scene(args.gaussians)
        vm = torch.eye(4)
    else:
        st = torch.load(args.state)
        means, quats, scales, opac, rgb = (a.float().contiguous() for a in st["args"])
        vm = st["viewmat"].float()
    cam = EquirectCamera(H, W)
    camv = raster_cpp.camera_vector(cam, 0.3, 0.01)
    dirs = raster_cpp.pixel_planes(cam, torch.float32)
    g = torch.Generator().manual_seed(1)
    grads = (torch.randn(H, W, 3, generator=g), 0.1 * torch.randn(H, W, generator=g),
             0.1 * torch.randn(H, W, generator=g))
    clock = time.thread_time if args.threads == 1 else time.perf_counter

    def run(m):
        t0 = clock()
        res = m.render_forward(means, quats, scales, opac, rgb, vm, dirs, camv, 16)
        t1 = clock()
        color, depth, Tf, last, P, bbox, toff, tlist, valid, radii, m2d, rot, hit = res
        gr = m.render_backward(*grads, means, quats, scales, opac, vm, dirs, camv, 16, P, bbox, toff, tlist, Tf,
                               last, valid, rot, hit)
        return t1 - t0, clock() - t0, (color, depth, Tf), gr

    out = {k: run(m) for k, m in mods.items()}
    fwd_diff = max(float((a - b).abs().max()) for a, b in zip(out["base"][2], out["this"][2]))
    print(f"{H}x{W}, {means.shape[0]:,} Gaussians; image/depth/alpha max difference {fwd_diff:.2e}")
    for name, a, b in zip(("means", "quats", "scales", "opacities", "rgb", "viewmat", "means2d"),
                          out["base"][3], out["this"][3]):
        rel = float((a - b).abs().max() / a.abs().max().clamp(min=1e-30))
        print(f"  gradient {name}: max difference {rel:.1e} of its largest value")
    times = {k: [] for k in mods}
    ratios = {"fwd": [], "fwd+bwd": []}
    for r in range(args.rounds):
        t = {}
        for k in (("base", "this") if r % 2 == 0 else ("this", "base")):
            t[k] = run(mods[k])[:2]
            times[k].append(t[k])
        ratios["fwd"].append(t["base"][0] / t["this"][0])
        ratios["fwd+bwd"].append(t["base"][1] / t["this"][1])
    for k, v in times.items():
        print(f"{k}: forward {statistics.median(x[0] for x in v) * 1e3:.1f} ms, "
              f"forward+backward {statistics.median(x[1] for x in v) * 1e3:.1f} ms (medians)")
    what = "CPU time of one thread" if args.threads == 1 else f"wall clock, {torch.get_num_threads()} threads"
    print(f"base/this, median of {args.rounds} per-pair ratios ({what}): forward "
          f"{statistics.median(ratios['fwd']):.2f}x, forward+backward {statistics.median(ratios['fwd+bwd']):.2f}x")


if __name__ == "__main__":
    main()
