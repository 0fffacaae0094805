"""Small files whose headers claim huge payloads: every decoder pano-pipe uses must refuse them from
the header (runfs/limits.py), before allocating what they claim. Shared by the hardening tests and
the fuzz suite's hostile-header generator."""

from __future__ import annotations

import struct
import zlib

import numpy as np


def png(width: int, height: int, bit_depth: int = 8, colour: int = 0, rows: int = 4) -> bytes:
    """A PNG whose IHDR says width x height; its data hold `rows` rows of zeros (a decoder that
    trusts the header allocates the whole image first)."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    channels = {0: 1, 2: 3, 4: 2, 6: 4}[colour]
    row_bytes = 1 + width * channels * bit_depth // 8
    rows = max(0, min(rows, height, (1 << 20) // row_bytes))  # at most 1 MB to compress here
    idat = zlib.compress(b"\x00" * (row_bytes * rows), 9)
    ihdr = struct.pack(">IIBBBBB", width, height, bit_depth, colour, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


def exr(width: int, height: int) -> bytes:
    """An OpenEXR header whose dataWindow is width x height (no pixel data)."""
    def attr(name: str, kind: str, value: bytes) -> bytes:
        return name.encode() + b"\x00" + kind.encode() + b"\x00" + struct.pack("<i", len(value)) + value

    channels = b"Y\x00" + struct.pack("<iBBBBii", 2, 0, 0, 0, 0, 1, 1) + b"\x00"
    window = struct.pack("<4i", 0, 0, width - 1, height - 1)
    header = (attr("channels", "chlist", channels) + attr("compression", "compression", b"\x00")
              + attr("dataWindow", "box2i", window) + attr("displayWindow", "box2i", window)
              + attr("lineOrder", "lineOrder", b"\x00") + attr("pixelAspectRatio", "float", struct.pack("<f", 1))
              + attr("screenWindowCenter", "v2f", struct.pack("<2f", 0, 0))
              + attr("screenWindowWidth", "float", struct.pack("<f", 1)) + b"\x00")
    return b"\x76\x2f\x31\x01" + struct.pack("<I", 2) + header + b"\x00" * 64


def npy(shape: tuple[int, ...], dtype: str = "<f4", payload: int = 64, header_pad: int = 0) -> bytes:
    """A .npy file whose header claims `shape`, holding `payload` bytes of data; `header_pad` makes
    the header that much longer (numpy refuses headers over 10 kB)."""
    header = repr({"descr": dtype, "fortran_order": False, "shape": tuple(shape)}).encode()
    header += b" " * header_pad
    header += b" " * (-(len(header) + 11) % 64) + b"\n"
    if len(header) < 65536:
        return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(header)) + header + b"\x00" * payload
    return b"\x93NUMPY\x02\x00" + struct.pack("<I", len(header)) + header + b"\x00" * payload


def real_npy(arr: np.ndarray) -> bytes:
    import io

    buf = io.BytesIO()
    np.save(buf, arr, allow_pickle=False)
    return buf.getvalue()


def ply(vertices: int, binary: bool = True, props: tuple[str, ...] = ("x", "y", "z", "opacity"),
        payload: int = 256) -> bytes:
    """A PLY whose header claims `vertices` vertices of float properties; `payload` bytes follow."""
    fmt = "binary_little_endian" if binary else "ascii"
    head = f"ply\nformat {fmt} 1.0\nelement vertex {vertices}\n"
    head += "".join(f"property float {p}\n" for p in props) + "end_header\n"
    body = b"\x00" * payload if binary else b"0 " * (payload // 2)
    return head.encode() + body


def colmap_points3d(track_length: int, points: int = 1) -> bytes:
    """points3D.bin with `points` points, the first claiming a track of `track_length` entries."""
    out = struct.pack("<Q", points)
    out += struct.pack("<Q3d3Bd", 1, 0.0, 0.0, 0.0, 0, 0, 0, 0.0) + struct.pack("<Q", track_length)
    return out + b"\x00" * 64


def colmap_images(points2d: int, images: int = 1) -> bytes:
    """images.bin with `images` images, the first claiming `points2d` 2D points."""
    out = struct.pack("<Q", images)
    out += struct.pack("<I4d3dI", 1, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1) + b"a.png\x00"
    return out + struct.pack("<Q", points2d) + b"\x00" * 64


def colmap_cameras(width: int, height: int, cameras: int = 1) -> bytes:
    """cameras.bin with one EQUIRECTANGULAR camera (model 17, 2 parameters) of width x height;
    `cameras` is the count the file claims."""
    return struct.pack("<Q", cameras) + struct.pack("<iiQQ2d", 1, 17, width, height, width, height)


def nan_model(ply_path) -> None:
    """Turn a binary little-endian float PLY model (ours) into one whose training diverged: every
    7th value NaN, every 11th Inf, the file's size unchanged (its artifact still matches it)."""
    from pathlib import Path

    data = Path(ply_path).read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    values = np.frombuffer(data[end:], "<f4").copy()
    values[::7] = np.nan
    values[3::11] = np.inf
    Path(ply_path).write_bytes(data[:end] + values.tobytes())
