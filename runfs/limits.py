"""Limits on every file pano-pipe decodes, checked from its header before anything is allocated.

A small file may claim a huge payload: a 259 KB PNG of 16000x8000, a 128-byte .npy claiming
1.5 TB, a PLY header claiming 10^12 vertices, a COLMAP points3D.bin claiming a track of 2^40
entries. Decoders allocate what the header claims before they find out the file is short, so the
claim is checked here first, in one place, by every reader: scene loading, the stages, the
importers, export and the viewer (docs/security.md, "Limits").

- Images (PNG, JPEG, EXR, ... incl. depth maps): at most `max_megapixels()` (default 64;
  `--max-megapixels` or PANO_PIPE_MAX_MEGAPIXELS), from the header.
- .npy: never pickles; the header's shape x dtype must fit in the file; at most
  `max_megapixels()` elements per 2-D map when `pixels=True`.
- PLY: the vertex count x record size must fit in the file (binary), or 2 bytes per value (ASCII).
- COLMAP binary models: every count (cameras, images, points, observations, track lengths) is
  walked against the bytes left in the file.
"""

from __future__ import annotations

import math
import os
import struct
from pathlib import Path

from runfs.errors import PanoError
from runfs.fsutil import native_stderr_off

#: Images over this many megapixels are refused before decoding (a 20000x10000 PNG of zeros is
#: 583 KB on disk and 600 MB decoded). `--max-megapixels` or PANO_PIPE_MAX_MEGAPIXELS change it.
DEFAULT_MAX_MEGAPIXELS = 64.0
#: The smallest panorama the stages can use (a pixel is 360/W degrees wide).
MIN_IMAGE_HEIGHT = 8


def max_megapixels() -> float:
    """The image-size limit in force: the environment's, else the default."""
    raw = os.environ.get("PANO_PIPE_MAX_MEGAPIXELS")
    if raw is None:
        return DEFAULT_MAX_MEGAPIXELS
    try:
        value = float(raw)
    except ValueError:
        raise PanoError("PANO_PIPE_MAX_MEGAPIXELS", f"must be a number of megapixels, got {raw!r}") from None
    if not value > 0 or not math.isfinite(value):
        raise PanoError("PANO_PIPE_MAX_MEGAPIXELS", f"must be a positive number, got {raw!r}")
    return value


# ----------------------------------------------------------------------------- images
def pixels_problem(h: int, w: int, limit_mp: float | None = None) -> str | None:
    """Why an H x W image (read, or about to be allocated at a working size) is over the pixel
    limit, or None. The one check behind images, depth maps and the settings that set a size."""
    limit_mp = max_megapixels() if limit_mp is None else limit_mp
    if h * w > limit_mp * 1e6:
        return f"is {w}x{h} ({h * w / 1e6:.0f} megapixels), over the limit of {limit_mp:g}"
    return None


def _exr_size(path: Path) -> tuple[int, int] | None:
    """(H, W) from an OpenEXR header's dataWindow attribute, or None if it is not one."""
    try:
        with open(path, "rb") as f:
            if f.read(4) != b"\x76\x2f\x31\x01":
                return None
            f.read(4)  # version and flags
            for _ in range(1000):  # attributes: name\0 type\0 size value; an empty name ends them
                name = _cstring(f)
                if not name:
                    return None
                _cstring(f)
                (size,) = struct.unpack("<i", f.read(4))
                if name == b"dataWindow" and size == 16:
                    x0, y0, x1, y1 = struct.unpack("<4i", f.read(16))
                    return y1 - y0 + 1, x1 - x0 + 1
                if size < 0:
                    return None
                f.seek(size, os.SEEK_CUR)
    except (OSError, struct.error):
        return None
    return None


def _cstring(f, limit: int = 256) -> bytes:
    out = bytearray()
    while len(out) < limit:
        c = f.read(1)
        if not c or c == b"\x00":
            break
        out += c
    return bytes(out)


def image_size(path: Path) -> tuple[int, int] | None:
    """(H, W) from the file header without decoding the pixels, or None if the header is not one
    Pillow (or the EXR reader here) reads."""
    from PIL import Image, UnidentifiedImageError

    if Path(path).suffix.lower() == ".exr":
        return _exr_size(path)
    try:
        with Image.open(path) as im:
            w, h = im.size
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError, struct.error):
        return None
    except Image.DecompressionBombError:  # Pillow's own limit; ours is checked by the caller
        return None
    return int(h), int(w)


def check_image_size(path: Path, limit_mp: float | None = None, min_height: int = MIN_IMAGE_HEIGHT,
                     what: str = "image") -> tuple[int, int] | None:
    """Refuse an image (or depth map) over `limit_mp` megapixels (default: `max_megapixels()`)
    or under `min_height` rows, from its header. Returns (H, W), or None when the header is not
    one we read (then `read_image` refuses to decode it)."""
    from PIL import Image

    Image.MAX_IMAGE_PIXELS = None  # Pillow would warn or refuse on its own terms; ours is clearer
    limit_mp = max_megapixels() if limit_mp is None else limit_mp
    hw = image_size(path)
    if hw is None:
        return None
    h, w = hw
    if h <= 0 or w <= 0:
        raise PanoError(path, f"{what} header claims {w}x{h} pixels")
    problem = pixels_problem(h, w, limit_mp)
    if problem:
        raise PanoError(path, f"{what} {problem}; resize it, or raise --max-megapixels")
    if h < min_height:
        raise PanoError(path, f"{what} is {w}x{h}; panoramas need at least {min_height} rows")
    return hw


def read_image(path: Path, flags: int | None = None, what: str = "image", min_height: int = 1,
               limit_mp: float | None = None):
    """cv2.imread under the size limit (checked from the header first); None if OpenCV cannot
    decode it. A file whose header we cannot read is left to OpenCV, under its own limit
    (CV_IO_MAX_IMAGE_PIXELS, 2^30 pixels by default)."""
    import cv2

    check_image_size(path, limit_mp, min_height=min_height, what=what)
    with native_stderr_off():  # libpng prints "libpng error: ..." itself; the caller says it in one line
        return cv2.imread(str(path), cv2.IMREAD_UNCHANGED if flags is None else flags)


# ----------------------------------------------------------------------------- .npy
def npy_header(path: Path) -> tuple[tuple[int, ...], object, int]:
    """(shape, dtype, data bytes in the file) from a .npy header, refusing pickles, a header that
    is not one, and a claim larger than the file."""
    import numpy as np

    path = Path(path)
    try:
        with open(path, "rb") as f:
            if f.read(6) != b"\x93NUMPY":  # np.load would otherwise try to unpickle it
                raise PanoError(path, "not a readable .npy array (no .npy header)")
            f.seek(0)
            fmt = np.lib.format
            version = fmt.read_magic(f)
            read_header = {(1, 0): fmt.read_array_header_1_0, (2, 0): fmt.read_array_header_2_0,
                           (3, 0): getattr(fmt, "read_array_header_2_0")}.get(version)
            if read_header is None:
                raise PanoError(path, f"not a readable .npy array (format version {version})")
            shape, _, dtype = read_header(f)
            data_bytes = os.fstat(f.fileno()).st_size - f.tell()
    except PanoError:
        raise
    except (ValueError, SyntaxError, TypeError) as e:  # numpy's header parser: too long, malformed
        raise PanoError(path, f"not a readable .npy array: {' '.join(str(e).split())[:160]}") from None
    except (OSError, EOFError) as e:
        raise PanoError(path, f"not a readable .npy array: {getattr(e, 'strerror', None) or e}") from None
    if dtype.hasobject:
        raise PanoError(path, "not a readable .npy array: it holds Python objects (pickled), which "
                              "pano-pipe never loads")
    # the header's claim checked against the file: np.load would allocate it first
    if math.prod(shape) * dtype.itemsize > data_bytes:
        raise PanoError(path, f"not a readable .npy array: its header claims shape {shape} of {dtype}, "
                              f"more than the file's {data_bytes} bytes of data")
    return shape, dtype, data_bytes


def load_npy(path: Path, pixels: bool = False):
    """A user's .npy array (never pickled objects), every failure a one-line PanoError naming it.
    `pixels`: a map (depth, boundaries) held to the image limit too."""
    import numpy as np

    path = Path(path)
    shape, _, _ = npy_header(path)
    if pixels and len(shape) >= 2 and shape[0] * shape[1] > max_megapixels() * 1e6:
        raise PanoError(path, f"array is {shape[1]}x{shape[0]} ({shape[0] * shape[1] / 1e6:.0f} megapixels), "
                              f"over the limit of {max_megapixels():g}; resize it, or raise --max-megapixels")
    try:
        return np.load(path, allow_pickle=False)
    except ValueError as e:
        raise PanoError(path, f"not a readable .npy array: {' '.join(str(e).split())[:160]}") from None
    except (OSError, EOFError) as e:
        raise PanoError(path, f"not a readable .npy array: {getattr(e, 'strerror', None) or e}") from None


# ----------------------------------------------------------------------------- PLY
def check_ply_count(path: Path, count: int, record_bytes: int, data_bytes: int, ascii_values: int = 0) -> None:
    """Refuse a PLY whose header claims more vertices than its body can hold: `record_bytes` per
    vertex (binary), or at least 2 bytes per value (ASCII: a digit and a separator)."""
    need = count * (2 * ascii_values if ascii_values else record_bytes)
    if count < 0 or need > data_bytes:
        raise PanoError(path, f"truncated or not a PLY we read: its header claims {count} vertices, more "
                              f"than the file's {data_bytes} bytes of data hold")


# ----------------------------------------------------------------------------- COLMAP
#: Parameters per COLMAP camera model id (colmap/sensor/models.h; pycolmap 4.2).
_COLMAP_PARAMS = {0: 3, 1: 4, 2: 4, 3: 5, 4: 8, 5: 8, 6: 12, 7: 5, 8: 4, 9: 5, 10: 12, 11: 16, 12: 4,
                  13: 5, 14: 3, 15: 4, 16: 6, 17: 2}


class _Reader:
    def __init__(self, path: Path):
        self.path = path
        self.f = open(path, "rb")
        self.size = os.fstat(self.f.fileno()).st_size

    def left(self) -> int:
        return self.size - self.f.tell()

    def unpack(self, fmt: str):
        n = struct.calcsize(fmt)
        data = self.f.read(n)
        if len(data) < n:
            raise PanoError(self.path, "truncated COLMAP binary file")
        return struct.unpack(fmt, data)

    def count(self, what: str, each: int) -> int:
        (n,) = self.unpack("<Q")
        if n * each > self.left():
            raise PanoError(self.path, f"claims {n} {what}, more than the file's {self.left()} bytes left hold")
        return n

    def skip(self, n: int) -> None:
        if n > self.left():
            raise PanoError(self.path, "truncated COLMAP binary file")
        self.f.seek(n, os.SEEK_CUR)

    def name(self) -> None:
        for _ in range(4096):
            c = self.f.read(1)
            if not c:
                raise PanoError(self.path, "truncated COLMAP binary file (an image name)")
            if c == b"\x00":
                return
        raise PanoError(self.path, "an image name longer than 4096 bytes")


def check_colmap_binary(model_dir: Path) -> None:
    """Walk cameras.bin, images.bin and points3D.bin (those present), refusing any count that
    claims more than the bytes left in its file, and cameras over the image limit."""
    limit = max_megapixels() * 1e6
    model_dir = Path(model_dir)
    path = model_dir / "cameras.bin"
    if path.is_file():
        r = _Reader(path)
        with r.f:
            for _ in range(r.count("cameras", 24)):
                _, model_id, width, height = r.unpack("<iiQQ")
                if model_id not in _COLMAP_PARAMS:
                    raise PanoError(path, f"unknown camera model id {model_id}")
                if width * height > limit:
                    raise PanoError(path, f"a camera of {width}x{height} pixels, over the limit of "
                                          f"{limit / 1e6:g} megapixels")
                r.skip(8 * _COLMAP_PARAMS[model_id])
    path = model_dir / "images.bin"
    if path.is_file():
        r = _Reader(path)
        with r.f:
            for _ in range(r.count("images", 64 + 1 + 8)):
                r.skip(4 + 8 * 7 + 4)
                r.name()
                r.skip(24 * r.count("2D points", 24))
    path = model_dir / "points3D.bin"
    if path.is_file():
        r = _Reader(path)
        with r.f:
            for _ in range(r.count("3D points", 43 + 8)):
                r.skip(8 + 24 + 3 + 8)
                r.skip(8 * r.count("track entries", 8))
