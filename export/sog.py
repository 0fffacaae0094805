"""PlayCanvas's SOG ("spatially ordered Gaussians", meta.json version 2), written and read in numpy.

A SOG is a meta.json and a few lossless WebP textures, bundled in an uncompressed zip (`.sog`)
or side by side in a folder. One texel per Gaussian, Gaussians in Morton (Z-curve) order of
their positions, every texture W×H with W = ⌈√N / 4⌉·4 and H = ⌈N / W / 4⌉·4, RGBA:

    means_l.webp, means_u.webp  low and high byte of a 16-bit (x, y, z): each coordinate as
                                l = sign(v)·ln(|v| + 1), mapped linearly from meta means.mins..maxs
                                (per axis, in l) to 0..65535; A = 255
    quats.webp                  "smallest three": the unit quaternion (w, x, y, z) times
                                sign(largest)·√2, its three other components as byte
                                255·(c/2 + ½) in (w, x, y, z) order, A = 252 + index of the largest
    scales.webp                 log scales x, y, z as indices into the 256-entry meta scales.codebook
    sh0.webp                    f_dc r, g, b as indices into the 256-entry meta sh0.codebook;
                                A = sigmoid(opacity)·255
    shN_labels.webp (SH > 0)    a 16-bit palette index per Gaussian (R low byte, G high byte)
    shN_centroids.webp          the palette: 64 entries a row, entry i at row i // 64, columns
                                (i % 64)·K' .. + K'-1 for its K' = (degree+1)²-1 coefficients, each
                                texel (r, g, b) indices into the 256-entry meta shN.codebook

as in PlayCanvas's splat-transform (src/lib/writers/write-sog.ts, readers/read-sog.ts), which
reads what this module writes (tests/export/test_export_sog.py converts it back to PLY with the
CLI). The coordinates are the PLY's (no axis change), so a SOG shows in a viewer as the .ply
does; `--y-up` rotates first, as for the other formats.

The codebooks (scales, sh0, the values of the SH palette) quantise all their values pooled
with splat-transform's 1-D quantiser (`quantize_1d`); the palette is a k-means of the Gaussians'
SH vectors (`kmeans`) with as many entries as splat-transform gives it (min(64, 2^⌊log2(N/1024)⌋)
·1024, at most N). Unlike splat-transform (which truncates), bytes are rounded to the nearest level.
"""

from __future__ import annotations

import io
import json
import math
import time
import zipfile
from pathlib import Path

import numpy as np

__all__ = ["SogData", "sog_encode", "sog_order", "zip_bytes", "write_sog", "read_sog", "texture_size",
           "palette_size", "kmeans", "quantize_1d", "pack_quats", "unpack_quats", "webp_encode",
           "webp_decode", "SOG_FILES"]

MEANS_FILES = ["means_l.webp", "means_u.webp"]
SHN_FILES = ["shN_centroids.webp", "shN_labels.webp"]
#: Every file a SOG folder may hold (meta.json names the ones it uses).
SOG_FILES = ["meta.json", *MEANS_FILES, "quats.webp", "scales.webp", "sh0.webp", *SHN_FILES]
_SQRT2 = math.sqrt(2.0)
_ZIP_TIME = (1980, 1, 1, 0, 0, 0)  # fixed, so the same model gives the same bytes


# ------------------------------------------------------------------ WebP (lossless, exact)
def webp_encode(rgba: np.ndarray) -> bytes:
    """Lossless WebP of an H×W×4 uint8 RGBA image, every channel exact (also the colour under
    alpha 0: the sh0 texture's alpha is opacity, and libwebp's default zeroes RGB where it is 0)."""
    import cv2

    rgba = np.ascontiguousarray(rgba, dtype=np.uint8)
    mode = getattr(cv2, "IMWRITE_WEBP_LOSSLESS_MODE", None)
    if mode is not None:  # OpenCV ≥ 4.12: lossless that keeps RGB under transparent texels
        ok, buf = cv2.imencode(".webp", cv2.cvtColor(rgba, cv2.COLOR_RGBA2BGRA),
                               [mode, cv2.IMWRITE_WEBP_LOSSLESS_PRESERVE_COLOR])
        if not ok:
            raise ValueError("OpenCV could not encode a WebP texture")
        return buf.tobytes()
    from PIL import Image  # older OpenCV: Pillow (matplotlib's dependency) with exact=True

    out = io.BytesIO()
    Image.fromarray(rgba, "RGBA").save(out, format="WEBP", lossless=True, exact=True, quality=100, method=4)
    return out.getvalue()


def webp_decode(data: bytes) -> np.ndarray:
    """H×W×4 uint8 RGBA of a WebP (an image stored without alpha gets A = 255)."""
    import cv2

    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None or img.dtype != np.uint8 or img.ndim not in (2, 3):
        raise ValueError("not a decodable 8-bit WebP image")
    if img.ndim == 2:
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2RGBA)
    elif img.shape[2] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGBA)
    else:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGBA)
    return img


# ------------------------------------------------------------------ quantisers
def quantize_1d(values: np.ndarray, k: int = 256, alpha: float = 0.5, bins: int = 1024
                ) -> tuple[np.ndarray, np.ndarray]:
    """A k-entry codebook (ascending) for 1-D `values` and each value's index into it (uint8 for
    k ≤ 256): splat-transform's 1-D quantiser. The sorted values are summarised by a `bins`-bin
    histogram whose bin edges blend quantile and uniform positions (the more the tails stretch
    the range beyond the interquartile one, the more quantile), each bin weighted by count^alpha
    (√: sparse tails keep entries); an exact dynamic programme splits the bins into k runs of
    least weighted squared error, each entry is its run's weighted mean, and every value takes
    its nearest entry. (Lloyd's k-means on the same histogram left 10× the largest error at the
    tails of the demo model's scales.)"""
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    dtype = np.uint8 if k <= 256 else np.int64
    if v.size == 0:
        return np.zeros(k), np.zeros(0, dtype)
    s = np.sort(v)
    n, lo, hi = s.size, s[0], s[-1]
    if hi - lo <= 1e-20:
        return np.full(k, lo), np.zeros(n, dtype)
    uniq = np.unique(s)
    if len(uniq) <= k:  # every distinct value an entry of its own: exact
        labels = np.searchsorted(uniq, v)
        return np.concatenate([uniq, np.full(k - len(uniq), uniq[-1])]), labels.astype(dtype)
    h = min(bins, n)
    iqr = s[int(n * 0.75)] - s[int(n * 0.25)]
    beta = max(0.5, min(0.999, 1.0 - iqr / (hi - lo)))
    pos = beta * np.arange(n) / n + (1 - beta) * (s - lo) / (hi - lo)
    b = np.minimum((h * pos).astype(np.int64), h - 1)
    cnt = np.bincount(b, minlength=h).astype(np.float64)
    keep = cnt > 0
    x = np.bincount(b, weights=s, minlength=h)[keep] / cnt[keep]
    w = cnt[keep] ** alpha
    m = len(x)
    kk = min(k, m)
    pw, pwx, pwxx = (np.concatenate([[0.0], np.cumsum(a)]) for a in (w, w * x, w * x * x))
    j_, a_ = np.meshgrid(np.arange(m), np.arange(m), indexing="ij")  # cost[j, a]: one run over bins a..j
    with np.errstate(divide="ignore", invalid="ignore"):
        cost = pwxx[j_ + 1] - pwxx[a_] - (pwx[j_ + 1] - pwx[a_]) ** 2 / (pw[j_ + 1] - pw[a_])
    cost = np.where(a_ <= j_, np.maximum(cost, 0.0), np.inf).astype(np.float32)  # float32: half the traffic
    dp = cost[:, 0].copy()  # one run over bins 0..j
    tail = np.ascontiguousarray(cost[:, 1:])  # [j, a-1]: the last run starts at a ≥ 1
    tot = np.empty_like(tail)
    rows = np.arange(m)
    splits = np.zeros((kk + 1, m), np.int64)
    for r in range(2, kk + 1):  # r runs over bins 0..j: the last starts at a ≥ r-1, the others cover 0..a-1
        np.add(tail, dp[None, :-1], out=tot)
        tot[:, : r - 2] = np.inf
        best = np.argmin(tot, axis=1)
        splits[r] = best + 1
        dp = tot[rows, best]
    code = np.empty(kk)
    j = m - 1
    for r in range(kk, 0, -1):
        a = splits[r, j] if r > 1 else 0
        code[r - 1] = (pwx[j + 1] - pwx[a]) / (pw[j + 1] - pw[a])
        j = a - 1
    code = np.unique(code)
    full = np.concatenate([code, np.full(k - len(code), code[-1])])  # padded with the last entry
    labels = np.searchsorted((code[1:] + code[:-1]) * 0.5, v)
    return full, labels.astype(dtype)


def kmeans(points: np.ndarray, k: int, iterations: int = 10, seed: int = 0, device: str | None = None,
           search: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Lloyd's k-means of N×D `points` into at most k clusters: (centroids, N labels).

    Equal points are clustered once, weighted by how often they occur (a trained model's SH is
    often all zero for many Gaussians); at most k distinct points are their own centroids, exactly.
    Otherwise the centroids start at k distinct random points, and an empty cluster is re-seeded
    at a random one. Each point's nearest centroid is found, on the CPU, with scipy's k-d tree over
    the centroids (as splat-transform does without a GPU: a trained model's SH vectors lie close to
    a few dimensions, and on the demo model the tree is ~5× faster than comparing every point with
    every centroid), and with one matrix product per block on a GPU (`device`, default: CUDA when
    torch sees one). `search` ("tree" or "matmul") overrides that choice."""
    import torch

    pts = np.ascontiguousarray(np.asarray(points, dtype=np.float32) + np.float32(0.0))  # -0 -> +0
    d = pts.shape[1]
    rows = pts.view(np.dtype((np.void, 4 * d))).reshape(-1)  # a row as one key: far faster than axis=0
    _, first, inverse, weight = np.unique(rows, return_index=True, return_inverse=True, return_counts=True)
    uniq, inverse = pts[first], inverse.reshape(-1)
    n = len(uniq)
    if k >= n:
        return uniq, inverse.astype(np.int64)
    dev = torch.device(device or ("cuda" if torch.cuda.is_available() else "cpu"))
    gen = np.random.default_rng(seed)
    p = torch.from_numpy(uniq).to(dev)
    w = torch.from_numpy(weight.astype(np.float64)).to(dev)
    pw = p.double() * w[:, None]
    c = p[torch.from_numpy(np.sort(gen.choice(n, k, replace=False))).to(dev)].clone()
    block = max(1, (1 << 24) // k)
    tree = (search or ("tree" if dev.type == "cpu" else "matmul")) == "tree"

    def assign() -> torch.Tensor:
        if tree:
            from scipy.spatial import cKDTree

            nearest = cKDTree(c.cpu().numpy()).query(uniq, workers=-1)[1]
            return torch.from_numpy(nearest.astype(np.int64)).to(dev)
        c2 = (c * c).sum(1)
        return torch.cat([torch.argmin(torch.addmm(c2, p[s:s + block], c.T, alpha=-2.0), dim=1)
                          for s in range(0, n, block)])

    for _ in range(iterations):
        labels = assign()
        counts = torch.zeros(k, dtype=torch.float64, device=dev).index_add_(0, labels, w)
        sums = torch.zeros(k, d, dtype=torch.float64, device=dev).index_add_(0, labels, pw)
        empty = counts == 0
        c = torch.where(empty[:, None], c, (sums / counts.clamp(min=1e-300)[:, None]).float())
        if bool(empty.any()):
            idx = gen.choice(n, int(empty.sum()), replace=False)
            c[empty] = p[torch.from_numpy(idx).to(dev)]
    labels = assign()
    return c.cpu().numpy(), labels.cpu().numpy()[inverse]


def _byte(x: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(x), 0, 255).astype(np.uint8)


_OTHERS = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])  # the components kept, by the largest


def pack_quats(q: np.ndarray) -> np.ndarray:
    """[N,4] (w,x,y,z) -> [N,4] uint8, the "smallest three" of quats.webp: the three smaller
    components of the unit quaternion times sign(largest)·√2 as bytes, then 252 + the largest's
    index."""
    n = len(q)
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    q = np.where(norm > 0, q / np.maximum(norm, 1e-300), np.array([1.0, 0, 0, 0]))
    big = np.argmax(np.abs(q), axis=1)  # the first of equal magnitudes, as splat-transform
    q = q * (np.where(q[np.arange(n), big] < 0, -1.0, 1.0) * _SQRT2)[:, None]
    out = np.empty((n, 4), np.uint8)
    out[:, :3] = _byte(255.0 * (np.take_along_axis(q, _OTHERS[big], axis=1) * 0.5 + 0.5))
    out[:, 3] = 252 + big
    return out


def unpack_quats(b: np.ndarray) -> np.ndarray:
    """[N,4] uint8 -> [N,4] unit (w,x,y,z): the inverse of pack_quats (as splat-transform decodes)."""
    b = b.astype(np.float64)
    n = len(b)
    big = (b[:, 3] - 252).astype(np.int64)
    small = (b[:, :3] / 255.0 * 2.0 - 1.0) / _SQRT2
    q = np.zeros((n, 4))
    np.put_along_axis(q, _OTHERS[big], small, axis=1)
    q[np.arange(n), big] = np.sqrt(np.maximum(0.0, 1.0 - (small ** 2).sum(1)))
    return q


# ------------------------------------------------------------------ layout
def texture_size(n: int) -> tuple[int, int]:
    """(width, height) of the per-Gaussian textures, as splat-transform lays them out."""
    w = int(math.ceil(math.sqrt(n) / 4)) * 4
    return w, int(math.ceil(n / w / 4)) * 4


def palette_size(n: int) -> int:
    """Entries of the SH palette for N Gaussians: splat-transform's min(64, 2^⌊log2(N/1024)⌋)·1024,
    at most N."""
    return max(1, min(n, int(min(64.0, 2.0 ** math.floor(math.log2(n / 1024))) * 1024)))


def _part1by2(v: np.ndarray) -> np.ndarray:
    v = v.astype(np.uint64) & np.uint64(0x3FF)
    for shift, mask in ((16, 0xFF0000FF), (8, 0x0300F00F), (4, 0x030C30C3), (2, 0x09249249)):
        v = (v ^ (v << np.uint64(shift))) & np.uint64(mask)
    return v


def sog_order(means: np.ndarray) -> np.ndarray:
    """Texel order: Gaussians sorted by the 30-bit Morton code of their positions in the
    bounding box (ties by index), so neighbouring texels hold nearby Gaussians and the
    textures compress."""
    m = np.asarray(means, dtype=np.float64)
    lo, ext = m.min(0), np.ptp(m, 0)
    mul = np.where(ext > 0, 1024.0 / np.where(ext > 0, ext, 1.0), 0.0)
    q = np.minimum((m - lo) * mul, 1023).astype(np.int64)
    code = (_part1by2(q[:, 2]) << np.uint64(2)) | (_part1by2(q[:, 1]) << np.uint64(1)) | _part1by2(q[:, 0])
    return np.argsort(code, kind="stable")


def _texture(n: int, cols: list[np.ndarray], alpha=255) -> np.ndarray:
    """An H×W×4 texture whose first n texels (row-major) hold the given byte columns."""
    w, h = texture_size(n)
    t = np.zeros((w * h, 4), np.uint8)
    for i, col in enumerate(cols):
        t[:n, i] = col
    t[:n, 3] = alpha
    return t.reshape(h, w, 4)


def _log_t(v: np.ndarray) -> np.ndarray:
    return np.sign(v) * np.log1p(np.abs(v))


def _codebook_json(code: np.ndarray) -> list[float]:
    return [float(f"{x:.8g}") for x in code]


# ------------------------------------------------------------------ writer
class SogData(dict):
    """The files of one SOG: name -> bytes (meta.json first), plus `order` (texel i holds
    Gaussian order[i]) and `seconds` spent on the SH palette."""

    order: np.ndarray
    seconds: float = 0.0


def sog_encode(g, iterations: int = 10) -> SogData:
    """The SOG files of the Gaussians `g` (gaussians.model.Gaussians, coordinates as they are)."""
    def arr(t):
        return t.detach().to("cpu").double().numpy()

    n = len(g)
    if n == 0:
        raise ValueError("a SOG holds at least one Gaussian")
    w, h = texture_size(n)
    if max(w, h) > 16383:
        raise ValueError(f"{n} Gaussians need {w}×{h} texels: beyond WebP's 16383")
    means = arr(g.means)
    if not np.all(np.isfinite(means)):
        raise ValueError("non-finite Gaussian positions cannot be stored in a SOG")
    order = sog_order(means)
    files = SogData()
    meta: dict = {"version": 2, "asset": {"generator": "pano-pipe"}, "count": n}

    # means: 16 bits per axis of the log-transformed coordinate between its min and max
    lt = _log_t(means[order])
    mins, maxs = lt.min(0), lt.max(0)
    span = np.where(maxs > mins, maxs - mins, 1.0)
    q = np.clip(np.rint(65535.0 * (lt - mins) / span), 0, 65535).astype(np.int64)
    tex = {"means_l.webp": _texture(n, [q[:, a] & 0xFF for a in range(3)]),
           "means_u.webp": _texture(n, [q[:, a] >> 8 for a in range(3)])}
    meta["means"] = {"mins": mins.tolist(), "maxs": maxs.tolist(), "files": list(MEANS_FILES)}

    # quaternions, smallest three
    packed = pack_quats(arr(g.quats)[order])
    tex["quats.webp"] = _texture(n, [packed[:, i] for i in range(3)], alpha=packed[:, 3])
    meta["quats"] = {"files": ["quats.webp"]}

    # scales and colours through 256-entry codebooks; opacity in sh0's alpha
    code, lab = quantize_1d(arr(g.log_scales)[order])
    lab = lab.reshape(n, 3)
    tex["scales.webp"] = _texture(n, [lab[:, i] for i in range(3)])
    meta["scales"] = {"codebook": _codebook_json(code), "files": ["scales.webp"]}
    code, lab = quantize_1d(arr(g.sh_dc).reshape(n, 3)[order])
    lab = lab.reshape(n, 3)
    alpha = _byte(255.0 / (1.0 + np.exp(-arr(g.opacity_logits)[order])))
    tex["sh0.webp"] = _texture(n, [lab[:, i] for i in range(3)], alpha=alpha)
    meta["sh0"] = {"codebook": _codebook_json(code), "files": ["sh0.webp"]}

    # higher SH bands: a palette of SH vectors (k-means), its values through a codebook
    degree = g.sh_degree
    if degree > 0:
        kc = (degree + 1) ** 2 - 1
        vec = arr(g.sh_rest)[order].transpose(0, 2, 1).reshape(n, 3 * kc)  # the PLY's channel-major f_rest
        t0 = time.perf_counter()
        cent, labels = kmeans(vec, palette_size(n), iterations=iterations)
        files.seconds = time.perf_counter() - t0
        # entries numbered by first use along the texels (nearby Gaussians, nearby numbers: the
        # labels texture compresses 3× better on the demo), unused ones dropped
        used, first = np.unique(labels, return_index=True)
        keep = used[np.argsort(first)]
        renumber = np.zeros(len(cent), np.int64)
        renumber[keep] = np.arange(len(keep))
        cent, labels = cent[keep], renumber[labels]
        m = len(cent)
        code, clab = quantize_1d(cent)
        clab = clab.reshape(m, 3, kc)
        rows = int(math.ceil(m / 64))
        pal = np.zeros((rows * 64, kc, 4), np.uint8)
        pal[:m, :, :3] = clab.transpose(0, 2, 1)
        pal[:m, :, 3] = 255
        tex["shN_centroids.webp"] = pal.reshape(rows, 64 * kc, 4)
        tex["shN_labels.webp"] = _texture(n, [labels & 0xFF, labels >> 8, np.zeros(n, np.uint8)])
        meta["shN"] = {"count": m, "bands": degree, "codebook": _codebook_json(code),
                       "files": list(SHN_FILES)}

    files["meta.json"] = json.dumps(meta, separators=(",", ":")).encode()
    for name, t in tex.items():
        files[name] = webp_encode(t)
    files.order = order
    return files


def zip_bytes(files: dict[str, bytes]) -> bytes:
    """The `.sog` bundle: the files in an uncompressed zip (WebP is compressed already), meta.json first."""
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", compression=zipfile.ZIP_STORED) as z:
        for name in sorted(files, key=lambda s: (s != "meta.json", s)):
            info = zipfile.ZipInfo(name, date_time=_ZIP_TIME)
            info.external_attr = 0o644 << 16
            z.writestr(info, files[name])
    return out.getvalue()


def write_sog(path: str | Path, g, iterations: int = 10) -> Path:
    """Write `g` as a `.sog` bundle at `path`."""
    path = Path(path)
    path.write_bytes(zip_bytes(sog_encode(g, iterations)))
    return path


# ------------------------------------------------------------------ reader
def _sog_source(path: Path):
    """(name -> bytes, meta.json's name) for the SOG at `path`: a .sog zip, a meta.json, or a folder
    holding one."""
    path = Path(path)
    if path.is_dir():
        path = path / "meta.json"
    if path.name.lower() == "meta.json" or path.suffix.lower() == ".json":
        folder = path.parent
        return lambda name: (folder / Path(name).name).read_bytes(), path.name
    try:
        z = zipfile.ZipFile(path)
    except zipfile.BadZipFile:
        raise ValueError(f"{path}: not a zip (a .sog is a zip of meta.json and WebP textures)") from None
    data = {i.filename: z.read(i) for i in z.infolist()}
    z.close()

    def get(name: str) -> bytes:
        if name not in data:
            raise ValueError(f"{path}: the bundle holds no {name}")
        return data[name]
    return get, "meta.json"


def read_sog(path: str | Path) -> "Gaussians":  # noqa: F821
    """Decode a SOG (meta.json version 2) into `Gaussians` (float32), texel order, coordinates as
    stored. Raises ValueError naming what is wrong with a malformed file."""
    import torch

    from gaussians.model import Gaussians

    path = Path(path)
    get, meta_name = _sog_source(path)
    try:
        meta = json.loads(get(meta_name))
    except (ValueError, OSError) as e:
        raise ValueError(f"{path}: unreadable meta.json ({e})") from None
    if not isinstance(meta, dict) or meta.get("version") != 2:
        raise ValueError(f"{path}: SOG meta version {meta.get('version') if isinstance(meta, dict) else '?'} "
                         "(version 2 is read here)")
    n = int(meta["count"])

    def tex(name: str) -> np.ndarray:
        try:
            t = webp_decode(get(name)).reshape(-1, 4)
        except OSError as e:
            raise ValueError(f"{path}: {name}: {e}") from None
        if len(t) < n:
            raise ValueError(f"{path}: {name} holds {len(t)} texels for {n} Gaussians")
        return t[:n].astype(np.int64)

    lo, hi = tex(meta["means"]["files"][0]), tex(meta["means"]["files"][1])
    mins, maxs = np.asarray(meta["means"]["mins"], float), np.asarray(meta["means"]["maxs"], float)
    span = np.where(maxs - mins != 0, maxs - mins, 1.0)
    lt = mins + span * (lo[:, :3] | (hi[:, :3] << 8)) / 65535.0
    means = np.sign(lt) * np.expm1(np.abs(lt))

    qt = tex(meta["quats"]["files"][0])
    if np.any((qt[:, 3] < 252) | (qt[:, 3] > 255)):
        raise ValueError(f"{path}: quats.webp holds a tag outside 252..255")
    quats = unpack_quats(qt)

    sc = np.asarray(meta["scales"]["codebook"], float)
    log_scales = sc[tex(meta["scales"]["files"][0])[:, :3]]
    c0 = tex(meta["sh0"]["files"][0])
    sh_dc = np.asarray(meta["sh0"]["codebook"], float)[c0[:, :3]]
    alpha = np.clip(c0[:, 3] / 255.0, 1e-6, 1 - 1e-6)

    sh_rest = np.zeros((n, 0, 3))
    shn = meta.get("shN")
    if shn:
        kc = (int(shn["bands"]) + 1) ** 2 - 1
        cb = np.asarray(shn["codebook"], float)
        pal = webp_decode(get(shn["files"][0])).astype(np.int64)
        if pal.shape[1] != 64 * kc:
            raise ValueError(f"{path}: shN_centroids.webp is {pal.shape[1]} wide, expected {64 * kc}")
        pal = pal.reshape(-1, kc, 4)[:, :, :3]  # entry, coefficient, channel
        lab = tex(shn["files"][1])
        label = lab[:, 0] | (lab[:, 1] << 8)
        if np.any(label >= min(len(pal), int(shn["count"]))):
            raise ValueError(f"{path}: an SH label beyond the palette's {shn['count']} entries")
        sh_rest = cb[pal[label]]  # [N, K-1, 3]

    t = lambda a: torch.as_tensor(np.ascontiguousarray(a), dtype=torch.float32)  # noqa: E731
    return Gaussians(
        means=t(means), quats=t(quats), log_scales=t(log_scales),
        opacity_logits=t(np.log(alpha / (1 - alpha))), sh_dc=t(sh_dc.reshape(n, 1, 3)), sh_rest=t(sh_rest),
        is_layout=torch.zeros(n, dtype=torch.bool), normals=torch.zeros(n, 3), u0=t(means),
    )
