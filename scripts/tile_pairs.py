"""The (tile, Gaussian) pairs the `cuda` rasteriser walks, with and without the tile test, per tile size.

    python scripts/tile_pairs.py [--height 512] [--tiles 16,8] [--gaussians 300000] [--ply MODEL.ply ...]

For `bench render`'s scene (its `indoor_scene`) and each trained model (seen from the median of its
centres): the pairs of the splats' pixel boxes, the share of them whose tile holds a pixel the
splat reaches (every pixel tested, float64), and the pairs left after the tile test
(splatting/bin_triton.py). The kernels run on the GPU where there is one, else in the Triton
interpreter (set here): 300k Gaussians at 512x1024 then take ~8 minutes a tile size.
Prints a markdown table (docs/gpu.md, "The tile test and the tile size").
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import torch

if not torch.cuda.is_available():
    os.environ.setdefault("TRITON_INTERPRET", "1")  # before anything imports triton
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from splatting import EquirectCamera, bin_triton  # noqa: E402
from splatting.bench import indoor_scene  # noqa: E402
from splatting.project_triton import project_gaussians  # noqa: E402
from splatting.reference import tiles_reached  # noqa: E402
from splatting.render import DEFAULT_EPS2D, _color_fn  # noqa: E402

DEVICE = "cuda" if torch.cuda.is_available() else "cpu"


def count(scene, camera, viewmat, ts):
    """(pairs in the boxes, share reaching a pixel, pairs walked after the tile test)."""
    with torch.no_grad():
        packed, ints, _, _ = project_gaussians(*scene, viewmat, camera, DEFAULT_EPS2D, 0.05, None, ts, _color_fn)
        walked = []
        for cull in (False, True):
            cap = bin_triton.PairCapacity(initial=1 << 23)
            toff, tlist, total = bin_triton.bin_gaussians(ints, camera.height, camera.width, ts, capacity=cap,
                                                          packed=packed if cull else None, camera=camera)
            walked.append((toff.cpu(), tlist.cpu()))
        toff, tlist = walked[0]
        counts = (toff[1:] - toff[:-1]).long()
        tiles = torch.repeat_interleave(torch.arange(counts.shape[0]), counts)
        share = float(tiles_reached(tiles, tlist[: int(toff[-1])], packed, camera, ts).float().mean())
    return int(walked[0][0][-1]), share, int(walked[1][0][-1])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--height", type=int, default=512)
    ap.add_argument("--tiles", default="16,8")
    ap.add_argument("--gaussians", type=int, default=300_000, help="bench render's scene size (0: leave it out)")
    ap.add_argument("--ply", action="append", default=[], help="a trained model (repeatable)")
    a = ap.parse_args(argv)
    camera = EquirectCamera(a.height, 2 * a.height)
    scenes = []
    if a.gaussians:
        scenes.append((f"`bench render`'s {a.gaussians:,}", indoor_scene(a.gaussians, 0), torch.eye(4)))
    from gaussians.ply import load_ply

    for path in a.ply:
        g = load_ply(path)
        viewmat = torch.eye(4)
        viewmat[:3, 3] = -g.means.median(0).values
        rgb = (g.sh_dc.reshape(len(g), 3) * 0.28209479177387814 + 0.5).clamp_min(0)  # the SH's DC term
        scenes.append((f"{path} ({len(g):,})", [g.means, g.quats, g.scales, g.opacities, rgb], viewmat))
    print(f"| scene ({a.height}x{2 * a.height}) | tile | pairs in the boxes | reaching a pixel | walked after the test |")
    print("|---|---|---|---|---|")
    for name, scene, viewmat in scenes:
        scene = [t.float().contiguous().to(DEVICE) for t in scene]
        for ts in (int(t) for t in a.tiles.split(",")):
            box, share, walked = count(scene, camera, viewmat.to(DEVICE), ts)
            print(f"| {name} | {ts}x{ts} | {box:,} | {share:.1%} | {walked:,} ({walked / box:.1%}) |", flush=True)


if __name__ == "__main__":
    main()
