"""The `cuda` backend's tile test (splatting/bin_triton.py): the tiles of a splat's pixel box it
culls hold no pixel the splat reaches, checked against every pixel of every culled tile, on the
hard cases (the ±180° seam, the poles, splats at the camera, sub-pixel and needle splats, tiles
that do not divide the image, pinhole crops), and it culls what a box over-covers. Without CUDA
the kernels run in the Triton interpreter."""

import math

import numpy as np
import pytest
import torch

pytest.importorskip("triton")

import splatting  # noqa: E402
from splatting import bin_triton  # noqa: E402
from splatting.project_triton import project_gaussians  # noqa: E402
from splatting.reference import tiles_reached  # noqa: E402
from splatting.render import _color_fn, _pixel_dirs  # noqa: E402

pytestmark = pytest.mark.cuda
DEVICE = torch.device("cuda" if torch.cuda.is_available() else "cpu")


def _scene(kind, n, seed):
    g = torch.Generator().manual_seed(seed)
    if kind == "seam":  # splats across ±180°, from pole to pole (issue 35's case)
        rng = np.random.default_rng(seed)
        phi = np.pi + rng.uniform(-0.2, 0.2, n)
        th = rng.uniform(-1.5, 1.5, n)
        means = torch.tensor(np.stack([np.cos(th) * np.sin(phi), -np.sin(th), np.cos(th) * np.cos(phi)], 1) * 2)
    else:
        means = (torch.rand(n, 3, generator=g, dtype=torch.float64) * 2 - 1) * (0.6 if kind == "near" else 3.0)
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    lo, hi = {"tiny": (-7.0, -4.0)}.get(kind, (-4.0, -0.5))
    scales = torch.exp(torch.rand(n, 3, generator=g, dtype=torch.float64) * (hi - lo) + lo)
    scales[:, 2] *= torch.where(torch.rand(n, generator=g) < 0.5, 0.01, 1.0).double()  # flat and needle splats
    opac = torch.rand(n, generator=g, dtype=torch.float64) * 0.98 + 0.01
    colors = torch.rand(n, 3, generator=g, dtype=torch.float64)
    return [t.to(torch.float32) for t in (means, quats / quats.norm(dim=1, keepdim=True), scales, opac, colors)]


def _pairs(toff, tlist):
    """The (tile, Gaussian) pairs of tile lists, as a set."""
    counts = (toff[1:] - toff[:-1]).long()
    tiles = torch.repeat_interleave(torch.arange(counts.shape[0]), counts)
    return set(zip(tiles.tolist(), tlist[: int(toff[-1])].long().tolist()))


def _reached(pairs, packed, camera, ts):
    """The pairs whose tile holds a pixel where the splat passes its cut-off, from every pixel
    (float64, with a relative slack of 1e-5 on τ: stricter than the float32 rasteriser)."""
    pairs = sorted(pairs)
    if not pairs:
        return set()
    tiles, gids = torch.tensor(pairs).T
    reached = tiles_reached(tiles, gids, packed, camera, ts, slack=1e-5)
    return {p for p, hit in zip(pairs, reached.tolist()) if hit}


def _bin(scene, camera, viewmat, ts, eps2d, cull):
    m, q, s, o, c = (t.to(DEVICE) for t in scene)
    with torch.no_grad():
        packed, ints, _, _ = project_gaussians(m, q, s, o, c, viewmat.to(DEVICE), camera, eps2d, 0.05, None, ts,
                                               _color_fn)
        cap = bin_triton.PairCapacity(initial=1 << 18)
        toff, tlist, total = bin_triton.bin_gaussians(ints, int(camera.height), int(camera.width), ts, capacity=cap,
                                                      packed=packed if cull else None, camera=camera)
    return _pairs(toff.cpu(), tlist.cpu()), packed, int(total)


def _turn(seed):
    R = torch.linalg.qr(torch.randn(3, 3, generator=torch.Generator().manual_seed(seed), dtype=torch.float64))[0]
    vm = torch.eye(4)
    vm[:3, :3] = R.float()
    return vm


# kind, camera, tile, eps2d, view (a random turn's seed, None: none), the least share of the tiles no
# pixel of which the splat reaches that the test must cull (it sees the tile's region, not its pixel
# centres: a sub-pixel splat between two centres stays)
CASES = [
    ("random", splatting.EquirectCamera(64, 128), 16, 0.3, 0, 0.5),
    ("random", splatting.EquirectCamera(50, 100), 8, 0.3, 1, 0.5),  # tiles that do not divide the image
    ("seam", splatting.EquirectCamera(64, 128), 8, 0.0, None, 0.5),
    ("near", splatting.EquirectCamera(64, 128), 13, 0.3, 2, 0.4),
    ("tiny", splatting.EquirectCamera(96, 192), 8, 0.0, 3, 0.0),
    ("random", splatting.EquirectCamera(24, 48), 16, 0.3, 4, 0.0),  # tiles wider than 90°: no test
    ("random", splatting.PinholeCamera(60.0, 60.0, 48.0, 40.0, 96, 80), 16, 0.3, 5, 0.5),
]


@pytest.mark.parametrize("kind, camera, ts, eps2d, view, least", CASES,
                         ids=[f"{k}-{c.width}x{c.height}-ts{t}" for k, c, t, *_ in CASES])
def test_culled_tiles_hold_no_pixel_the_splat_reaches(kind, camera, ts, eps2d, view, least):
    scene = _scene(kind, 400, seed=ts)
    vm = torch.eye(4) if view is None else _turn(view)
    box, packed, total = _bin(scene, camera, vm, ts, eps2d, cull=False)
    kept, _, total_culled = _bin(scene, camera, vm, ts, eps2d, cull=True)
    assert total == total_culled == len(box)  # the list's capacity is the boxes' count either way
    assert kept <= box
    culled = box - kept
    assert not (_reached(culled, packed, camera, ts)), "a culled tile holds a pixel the splat reaches"
    if bin_triton.tile_corners(camera, ts, torch.float32, "cpu") is None:
        assert kept == box
    else:  # the test does something: the tiles that nothing reaches are culled
        empty = box - _reached(box, packed, camera, ts)
        assert len(empty) > 0.05 * len(box) and len(culled) >= least * len(empty), (len(box), len(empty), len(culled))


def test_the_corner_region_holds_every_pixel_centre_of_its_tile():
    """Every pixel direction of a tile lies inside the region its corner tables span (on the
    tile's own tangent plane): the one fact the test's conservativeness rests on."""
    cam, ts = splatting.EquirectCamera(64, 128), 16
    rows, cols = bin_triton.tile_corners(cam, ts, torch.float64, "cpu")
    dirs = _pixel_dirs(cam, torch.float64, "cpu").reshape(64, 128, 3)
    for tr in range(rows.shape[0]):
        for tc in range(cols.shape[0]):
            (a0, a1, b0, b1), (l0, l1, r0, r1) = rows[tr].tolist(), cols[tc].tolist()
            corners = torch.tensor([[a0 * l0, a1, a0 * l1], [a0 * r0, a1, a0 * r1], [b0 * r0, b1, b0 * r1],
                                    [b0 * l0, b1, b0 * l1]], dtype=torch.float64)
            d = dirs[tr * ts:(tr + 1) * ts, tc * ts:(tc + 1) * ts].reshape(-1, 3)
            # inside the spherical quadrilateral: on the inner side of each edge's great circle
            centre = corners.sum(0)
            for k in range(4):
                normal = torch.linalg.cross(corners[k], corners[(k + 1) % 4])
                if normal.norm() < 1e-12:  # the two corners of a pole tile's top edge coincide
                    continue
                side = math.copysign(1.0, float(normal @ centre))
                assert bool((side * (d @ normal) >= -1e-12).all()), (tr, tc, k)
