"""Niantic's .spz (version 3; version 2 is read too), written and read in numpy.

No maintained Python package could be used (docs/export.md says why), so this follows
the format as Niantic's reference implementation (nianticlabs/spz, load-spz.cc) packs
it: a gzip stream holding a 16-byte little-endian header

    uint32 magic 0x5053474e ("NGSP"), uint32 version (3), uint32 numPoints,
    uint8 shDegree, uint8 fractionalBits (12), uint8 flags (0), uint8 reserved (0)

then, attribute by attribute for all Gaussians:

    positions  3 × 24-bit signed fixed point, `fractionalBits` fractional bits
    alphas     1 × uint8  sigmoid(opacity)·255
    colors     3 × uint8  f_dc·(0.15·255) + 127.5  (wider than [0,1] on purpose)
    scales     3 × uint8  (log scale + 10)·16
    rotations  v3: 4 bytes, a little-endian uint32 holding the index of the largest |component|
               of the unit quaternion (x, y, z, w order; 2 bits) and the other three as sign + 9-bit
               magnitude of |q_i|/√½ ("smallest three"); v2: 3 × uint8 x, y, z with w ≥ 0,
               q·127.5 + 127.5 (poorly conditioned where w ≈ 0, which is why v3 replaced it)
    sh         (K-1)·3 × uint8  coefficient-major, colour-minor; round(c·128) + 128,
               bucketed to 5 bits for band 1 and 4 bits for bands 2-3

Coordinates: SPZ stores RUB (x right, y up, z back). pano-pipe's world is RDF (OpenCV,
y down), so writing applies (x, y, z) -> (x, -y, -z) to positions, the quaternion's
y and z and the SH bases' odd terms -- exactly export.transform.to_y_up. The reader
undoes it, so a file round-trips into the y-down world; a y-up model (--y-up) is
already RUB and is stored as is. Both give the same file.
"""

from __future__ import annotations

import gzip
import struct
import math
from pathlib import Path

import numpy as np
import torch

from gaussians.model import Gaussians

__all__ = ["MAGIC", "spz_bytes", "write_spz", "read_spz", "spz_header"]

MAGIC = 0x5053474E
VERSION = 3
FRACTIONAL_BITS = 12
COLOR_SCALE = 0.15
SH1_BITS = 5
SH_REST_BITS = 4
_HEADER = struct.Struct("<IIIBBBB")
#: Largest |coordinate| a 24-bit fixed point with 12 fractional bits holds (metres).
MAX_COORD = (2 ** 23 - 1) / 2 ** FRACTIONAL_BITS


def _u8(x: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(x), 0, 255).astype(np.uint8)


def _quantize_sh(x: np.ndarray, bits: int) -> np.ndarray:
    bucket = 1 << (8 - bits)
    q = np.rint(x * 128.0).astype(np.int64) + 128
    q = (q + bucket // 2) // bucket * bucket
    return np.clip(q, 0, 255).astype(np.uint8)


_SQRT1_2 = math.sqrt(0.5)


def _pack_smallest_three(q_wxyz: np.ndarray) -> np.ndarray:
    """[N,4] (w,x,y,z) -> [N,4] uint8: SPZ v3's smallest-three packing (x, y, z, w order)."""
    q = q_wxyz[:, [1, 2, 3, 0]]
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    q = np.where(norm > 0, q / np.maximum(norm, 1e-30), np.array([0.0, 0, 0, 1]))
    largest = np.argmax(np.abs(q), axis=1)
    negate = q[np.arange(len(q)), largest] < 0
    comp = largest.astype(np.uint64)
    for i in range(4):
        use = largest != i
        negbit = ((q[:, i] < 0) ^ negate).astype(np.uint64)
        mag = np.minimum(np.floor(511.0 * np.abs(q[:, i]) / _SQRT1_2 + 0.5), 511).astype(np.uint64)
        comp = np.where(use, (comp << np.uint64(10)) | (negbit << np.uint64(9)) | mag, comp)
    comp = comp.astype(np.uint32)
    return comp.astype("<u4").view(np.uint8).reshape(-1, 4)


def _unpack_smallest_three(b: np.ndarray) -> np.ndarray:
    """[N,4] uint8 -> [N,4] (w,x,y,z)."""
    comp = b.astype(np.uint8).copy().view("<u4").reshape(-1).astype(np.int64)
    largest = comp >> 30
    q = np.zeros((len(comp), 4))
    for i in (3, 2, 1, 0):
        use = largest != i
        mag = comp & 511
        val = _SQRT1_2 * mag / 511.0 * np.where((comp >> 9) & 1, -1.0, 1.0)
        q[:, i] = np.where(use, val, 0.0)
        comp = np.where(use, comp >> 10, comp)
    rest = (q ** 2).sum(1)
    q[np.arange(len(q)), largest] = np.sqrt(np.maximum(0.0, 1.0 - rest))
    return q[:, [3, 0, 1, 2]]


def spz_bytes(g: Gaussians, rub: bool = False) -> bytes:
    """The .spz file content. `rub=True`: `g` is already in a y-up (RUB) frame, store it as is;
    otherwise `g` is in pano-pipe's y-down world and is rotated into RUB first."""
    from export.transform import to_y_up

    if not rub:
        g = to_y_up(g)
    n = len(g)
    degree = g.sh_degree

    def arr(t: torch.Tensor) -> np.ndarray:
        return t.detach().to("cpu").double().numpy()

    means = arr(g.means)
    if n and not np.all(np.isfinite(means)):
        raise ValueError("non-finite Gaussian positions cannot be stored in .spz")
    if n and np.abs(means).max() > MAX_COORD:
        raise ValueError(f"a position beyond ±{MAX_COORD:.0f} m does not fit .spz's 24-bit fixed point")
    fixed = np.rint(means * (1 << FRACTIONAL_BITS)).astype(np.int64).reshape(-1) & 0xFFFFFF
    positions = np.stack([fixed & 0xFF, (fixed >> 8) & 0xFF, (fixed >> 16) & 0xFF], 1).astype(np.uint8)

    alphas = _u8(255.0 / (1.0 + np.exp(-arr(g.opacity_logits))))
    colors = _u8(arr(g.sh_dc).reshape(n, 3) * (COLOR_SCALE * 255.0) + 127.5)
    scales = _u8((arr(g.log_scales) + 10.0) * 16.0)
    rotations = _pack_smallest_three(arr(g.quats))
    parts = [positions.tobytes(), alphas.tobytes(), colors.tobytes(), scales.tobytes(), rotations.tobytes()]
    if degree > 0:
        rest = arr(g.sh_rest)  # [N, K-1, 3]: coefficient-major, colour-minor, as SPZ wants
        sh = np.empty(rest.shape, dtype=np.uint8)
        sh[:, :3] = _quantize_sh(rest[:, :3], SH1_BITS)
        sh[:, 3:] = _quantize_sh(rest[:, 3:], SH_REST_BITS)
        parts.append(sh.tobytes())
    header = _HEADER.pack(MAGIC, VERSION, n, degree, FRACTIONAL_BITS, 0, 0)
    return gzip.compress(header + b"".join(parts), mtime=0)


def write_spz(path: str | Path, g: Gaussians, rub: bool = False) -> Path:
    path = Path(path)
    path.write_bytes(spz_bytes(g, rub=rub))
    return path


def spz_header(raw: bytes) -> dict:
    magic, version, n, degree, frac, flags, reserved = _HEADER.unpack_from(raw, 0)
    return {"magic": magic, "version": version, "num_points": n, "sh_degree": degree,
            "fractional_bits": frac, "flags": flags, "reserved": reserved}


def read_spz(path: str | Path, rub: bool = False) -> Gaussians:
    """Decode a version-2 or -3 .spz into `Gaussians` (float32), in pano-pipe's y-down world
    unless `rub`. Raises ValueError naming what is wrong with a malformed file."""
    from export.transform import to_y_up

    try:
        raw = gzip.decompress(Path(path).read_bytes())
    except (OSError, EOFError) as e:
        raise ValueError(f"{path}: not a gzip stream ({e})") from None
    if len(raw) < _HEADER.size:
        raise ValueError(f"{path}: shorter than the 16-byte SPZ header")
    h = spz_header(raw)
    if h["magic"] != MAGIC:
        raise ValueError(f"{path}: bad magic {h['magic']:#x} (not an SPZ file)")
    if h["version"] not in (2, 3):
        raise ValueError(f"{path}: SPZ version {h['version']} (versions 2 and 3 are read here)")
    if h["flags"] & 0x2:
        raise ValueError(f"{path}: SPZ extensions are not read here")
    n, degree = h["num_points"], h["sh_degree"]
    if degree > 3:
        raise ValueError(f"{path}: SH degree {degree} (pano-pipe holds at most 3)")
    k1 = (degree + 1) ** 2 - 1
    rot_bytes = 4 if h["version"] >= 3 else 3
    sizes = [9 * n, n, 3 * n, 3 * n, rot_bytes * n, 3 * k1 * n]
    if len(raw) != _HEADER.size + sum(sizes):
        raise ValueError(f"{path}: {len(raw) - _HEADER.size} data bytes, expected {sum(sizes)} for {n} points")
    buf = np.frombuffer(raw, dtype=np.uint8, offset=_HEADER.size)
    chunks = np.split(buf, np.cumsum(sizes)[:-1])
    p = chunks[0].reshape(n * 3, 3).astype(np.int64)
    fixed = p[:, 0] | (p[:, 1] << 8) | (p[:, 2] << 16)
    fixed = np.where(fixed & 0x800000, fixed - (1 << 24), fixed)
    means = (fixed / float(1 << h["fractional_bits"])).reshape(n, 3)
    alpha = np.clip(chunks[1].astype(np.float64) / 255.0, 1e-6, 1 - 1e-6)
    sh_dc = (chunks[2].astype(np.float64).reshape(n, 3) / 255.0 - 0.5) / COLOR_SCALE
    log_scales = chunks[3].astype(np.float64).reshape(n, 3) / 16.0 - 10.0
    if rot_bytes == 4:
        quats = _unpack_smallest_three(chunks[4].reshape(n, 4))
    else:
        xyz = chunks[4].astype(np.float64).reshape(n, 3) / 127.5 - 1.0
        quats = np.concatenate([np.sqrt(np.maximum(0.0, 1.0 - (xyz ** 2).sum(1, keepdims=True))), xyz], 1)
    rest = (chunks[5].astype(np.float64).reshape(n, k1, 3) - 128.0) / 128.0
    t = lambda a: torch.as_tensor(a, dtype=torch.float32)  # noqa: E731
    g = Gaussians(
        means=t(means), quats=t(quats), log_scales=t(log_scales),
        opacity_logits=t(np.log(alpha / (1 - alpha))), sh_dc=t(sh_dc.reshape(n, 1, 3)), sh_rest=t(rest),
        is_layout=torch.zeros(n, dtype=torch.bool), normals=torch.zeros(n, 3), u0=t(means),
    )
    return g if rub else to_y_up(g)


