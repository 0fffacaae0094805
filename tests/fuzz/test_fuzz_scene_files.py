"""Fuzz the files a scene supplies: images, layouts (.json/.txt/.npy) and depth maps (.png/.npy)."""

from __future__ import annotations

import io
import json
import struct
import zlib

import cv2
import numpy as np
from hypothesis import example, given
from hypothesis import strategies as st

from fuzz_helpers import (
    FAST_STAGES,
    NUMBERS,
    SCENE_VIEWS,
    fuzz_settings,
    json_dumps_deep,
    deep,
    run_args,
    run_example,
    sandbox,
)

NAN, INF = float("nan"), float("inf")
H, W = 16, 32  # the base scene's panorama size


# ----------------------------------------------------------------------------- file contents
def png_bomb(width: int, height: int) -> bytes:
    """A PNG header claiming width x height RGB pixels, then a few bytes of (truncated) data."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    idat = zlib.compress(b"\x00" * 4096)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


def npy_bytes(arr: np.ndarray, fortran: bool = False) -> bytes:
    buf = io.BytesIO()
    np.save(buf, np.asfortranarray(arr) if fortran else arr, allow_pickle=True)
    return buf.getvalue()


def fill_array(shape, dtype: str, fill: str, kind: str) -> np.ndarray:
    """An array of `shape`; `fill` says what values (valid ones depend on `kind`: layout or depth)."""
    rng = np.random.default_rng(0)
    if kind == "layout":  # [2,W] latitudes: ceiling > 0, floor < 0
        valid = np.zeros(shape)
        if len(shape) >= 1 and shape[0] >= 1:
            valid[0] = 0.5
        if len(shape) >= 1 and shape[0] >= 2:
            valid[1] = -0.6
    else:  # depth in metres
        valid = rng.uniform(1.0, 5.0, size=shape)
    values = {
        "valid": valid,
        "nan": np.full(shape, NAN),
        "inf": np.full(shape, INF),
        "neg": -np.abs(valid) - 1,
        "zero": np.zeros(shape),
        "huge": np.full(shape, 1e308),
        "tiny": np.full(shape, 1e-300),
        "random": rng.normal(0, 10, size=shape),
        "swapped": -valid,
        "some_nan": np.where(rng.random(shape) < 0.3, NAN, valid),
        "out_of_range": valid * 10,
    }[fill]
    if dtype == "object":
        out = np.empty(shape, dtype=object)
        out[...] = values.tolist() if shape else values.item()
        return out
    if dtype == "structured":
        out = np.zeros(shape, dtype=[("a", "f4"), ("b", "i4")])
        out["a"] = values
        return out
    with np.errstate(all="ignore"):
        try:
            return values.astype(dtype)
        except (TypeError, ValueError):
            return np.zeros(shape, dtype=dtype)


dtypes = st.sampled_from(["float64", "float32", "float16", "int32", "uint16", "int8", "bool",
                          "complex64", "object", "structured", ">f8", "datetime64[s]"])
fills = st.sampled_from(["valid", "nan", "inf", "neg", "zero", "huge", "tiny", "random", "swapped",
                         "some_nan", "out_of_range"])

#: Files with a .npy name that are not plain numeric arrays.
npy_specials = st.sampled_from(["pickle", "garbage", "truncated", "fortran", "empty", "text", "huge_header",
                                "claims_huge", "npz"])


def special_npy(kind: str, valid: np.ndarray) -> bytes:
    if kind == "pickle":  # an object array holding a dict: loading it needs allow_pickle
        return npy_bytes(np.array([{"uv": [0.5]}, None], dtype=object))
    if kind == "garbage":
        return b"\x93NUMPY\x01\x00garbage"
    if kind == "empty":
        return b""
    if kind == "text":
        return b"0.5 0.5\n-0.6 -0.6\n"
    if kind == "huge_header":
        return b"\x93NUMPY\x01\x00\xff\xff" + b"{" * 100
    if kind == "truncated":
        raw = npy_bytes(valid)
        return raw[: len(raw) // 2]
    if kind == "fortran":
        return npy_bytes(valid, fortran=True)
    if kind == "claims_huge":  # a valid header for 2 x 1e11 float64, then 64 bytes of data
        header = b"{'descr': '<f8', 'fortran_order': False, 'shape': (2, 100000000000), }"
        header += b" " * (-(len(header) + 11) % 64) + b"\n"
        return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(header)) + header + b"\x00" * 64
    if kind == "npz":
        buf = io.BytesIO()
        np.savez(buf, a=valid)
        return buf.getvalue()
    raise AssertionError(kind)


# ----------------------------------------------------------------------------- images
IMAGE_SHAPES = [(16, 32, 3), (10, 10, 3), (1, 2, 3), (2, 1, 3), (1, 1, 3), (16, 32), (16, 32, 1),
                (16, 32, 4), (16, 32, 2), (4, 8, 3), (7, 14, 3), (8, 16, 3), (32, 64, 3), (17, 34, 3),
                (16, 33, 3), (0, 0, 3)]

image_contents = st.one_of(
    st.just(("empty",)),
    st.tuples(st.just("truncate"), st.floats(0.0, 1.0)),
    st.tuples(st.just("bytes"), st.binary(max_size=64)),
    st.tuples(st.just("text"), st.sampled_from(["not a png", "[/b] error", "P6\n99999 99999\n255\n",
                                                "BM" + "\x00" * 60])),
    st.tuples(st.just("array"), st.sampled_from(IMAGE_SHAPES), st.sampled_from(["uint8", "uint16", "float32"]),
              st.sampled_from([".png", ".jpg", ".bmp", ".tiff", ".webp", ".pgm", ".exr"])),
    st.tuples(st.just("bomb"), st.sampled_from([(12000, 6000), (40000, 20000), (2 ** 31 - 1, 1), (2, 1), (0, 0)])),
    st.just(("dir",)),
    st.just(("npy",)),
)


def write_image(sb, view: str, content) -> None:
    data = sb.manifest()
    path = sb.scene / "images" / f"{view}.png"
    kind = content[0]
    if kind == "dir":
        path.unlink()
        path.mkdir()
        (path / "x.png").write_bytes(b"")
        return
    if kind == "empty":
        path.write_bytes(b"")
    elif kind == "truncate":
        raw = path.read_bytes()
        path.write_bytes(raw[: int(len(raw) * content[1])])
    elif kind == "bytes":
        path.write_bytes(content[1])
    elif kind == "text":
        path.write_text(content[1])
    elif kind == "bomb":
        path.write_bytes(png_bomb(*content[1]))
    elif kind == "npy":
        path.write_bytes(npy_bytes(np.zeros((16, 32, 3), np.uint8)))
    elif kind == "array":
        shape, dtype, ext = content[1:]
        rng = np.random.default_rng(1)
        scale = {"uint8": 255, "uint16": 65535, "float32": 1.0}[dtype]
        arr = (rng.random(shape) * scale).astype(dtype)
        try:
            ok, buf = cv2.imencode(ext, arr)
        except cv2.error:
            ok, buf = False, None
        if not ok:  # the codec refuses this array: write it as PNG, or as raw bytes
            ext = ".png"
            try:
                ok, buf = cv2.imencode(ext, arr)
            except cv2.error:
                ok, buf = False, None
        raw = buf.tobytes() if ok else arr.tobytes()
        new = path.with_suffix(ext)
        path.unlink()
        new.write_bytes(raw)
        sb.view(data, view)["image"] = f"images/{new.name}"
        sb.write_manifest(data)


@given(
    view=st.sampled_from(SCENE_VIEWS),
    content=image_contents,
    until=st.sampled_from(FAST_STAGES),
)
@example(view="train_00", content=("bomb", (40000, 20000)), until="layout")
@example(view="train_01", content=("array", (1, 2, 3), "uint8", ".png"), until="align")
@example(view="train_02", content=("array", (16, 32, 2), "uint16", ".tiff"), until="align")
@example(view="test_00", content=("truncate", 0.5), until="layout")
@example(view="train_00", content=("empty",), until="layout")
@fuzz_settings(max_examples=25)
def test_image_mutations(view, content, until, fuzz_base, tmp_path, capfd):
    with sandbox(fuzz_base, tmp_path) as sb:
        write_image(sb, view, content)
        run_example(sb, run_args(until), capfd, (view, content, until), "images")


# ----------------------------------------------------------------------------- layouts
uv_number = st.one_of(st.floats(0.0, 1.0), st.sampled_from([NAN, INF, -INF, -0.0, 0.0, 1.0, 2.0, -1.0, 1e308,
                                                            0.5, 0.4999, 0.5001, True]))
z_value = st.one_of(st.sampled_from(NUMBERS), st.none(), st.text(max_size=4), st.just([1.0]))

PERTURBS = ["drop_point", "swap_pair", "reverse", "same_u", "duplicate", "two_corners", "self_intersect",
            "horizon", "poles", "z_swap", "z_zero", "many", "tiny_room", "wrap", "shuffle"]

layout_json = st.one_of(
    st.tuples(st.just("uv"), st.lists(st.lists(uv_number, min_size=0, max_size=3), max_size=12), z_value, z_value),
    st.tuples(st.just("value"), st.recursive(
        st.one_of(st.none(), st.booleans(), st.sampled_from(NUMBERS), st.text(max_size=5)),
        lambda kids: st.one_of(st.lists(kids, max_size=3), st.dictionaries(
            st.sampled_from(["uv", "z0", "z1", "cor", "x"]), kids, max_size=3)),
        max_leaves=8)),
    st.tuples(st.just("perturb"), st.sampled_from(PERTURBS)),
    st.tuples(st.just("raw"), st.sampled_from(['{"uv": [[0.1, 0.2]', '{"uv": NaN}', "[/x] 1", "",
                                               '{"uv": [[0.1, 0.3], [0.1, 0.7]], "uv": 5}'])),
    st.tuples(st.just("raw_bytes"), st.sampled_from([b"\xff\xfe{", b'{"uv": "\xc3("}', b"\x00" * 10])),
    st.tuples(st.just("deep"), st.sampled_from([100, 100_000])),
)

txt_number = st.one_of(st.floats(-1.0, 40.0), st.sampled_from([NAN, INF, 1e308, -0.5, 31.5, 15.5, 7.5, 7.4999, 0.0]))
txt_line = st.one_of(
    st.tuples(txt_number, txt_number).map(lambda p: f"{p[0]!r} {p[1]!r}"),
    st.sampled_from(["[/x] 1", "[red]1 2[/red]", "[/]", "1,2", "# comment", "", "1 2 3", "nan nan", "inf 1",
                     "1e308 1e308", "0x10 5", "١ ٢", "1_000 2", "  4 5  ", "\x00", "1 2 # x", "+1 -1", "x y"]),
)
layout_txt = st.one_of(
    st.tuples(st.just("lines"), st.lists(txt_line, max_size=14)),
    st.tuples(st.just("perturb"), st.sampled_from(PERTURBS)),
    st.tuples(st.just("raw_bytes"), st.sampled_from([b"\xff\xfe1 2\n", b"1 2\n\xc3(\n", b"1 2\r3 4\r5 6\r7 8\r9 10\r11 12"])),
)

LAYOUT_NPY_SHAPES = [(2, 32), (2, 8), (2, 7), (32, 2), (2,), (3, 32), (2, 32, 1), (), (0,), (2, 0), (1, 32),
                     (2, 1000), (2, 33)]
layout_npy = st.one_of(
    st.tuples(st.just("array"), st.sampled_from(LAYOUT_NPY_SHAPES), dtypes, fills),
    st.tuples(st.just("special"), npy_specials),
)

layout_files = st.one_of(
    st.tuples(st.just(".json"), layout_json),
    st.tuples(st.just(".txt"), layout_txt),
    st.tuples(st.just(".npy"), layout_npy),
    st.tuples(st.sampled_from([".JSON", ".yaml", ".png", ""]), st.just(("raw", '{"uv": []}'))),
)


def base_corners(sb) -> tuple[list, float, float]:
    """The uv corner list and z0/z1 of the base scene's train_00 layout (valid)."""
    data = json.loads((sb.scene / "layout" / "train_00.json").read_text())
    return [list(p) for p in data["uv"]], data.get("z0", 1.0), data.get("z1", -1.6)


def perturb(uv: list, z0: float, z1: float, how: str):
    uv = [list(p) for p in uv]
    pairs = [uv[i: i + 2] for i in range(0, len(uv), 2)]
    if how == "drop_point":
        uv = uv[:-1]
    elif how == "swap_pair":
        pairs[0] = pairs[0][::-1]
        pairs[0][0][1], pairs[0][1][1] = pairs[0][1][1], pairs[0][0][1]
        uv = [p for pair in pairs for p in pair]
        uv[0][1], uv[1][1] = 1 - uv[0][1], 1 - uv[1][1]
    elif how == "reverse":
        uv = [p for pair in pairs[::-1] for p in pair]
    elif how == "same_u":
        uv = [[0.5, p[1]] for p in uv]
    elif how == "duplicate":
        uv = uv + uv
    elif how == "two_corners":
        uv = uv[:4]
    elif how == "self_intersect":
        pairs[0], pairs[1] = pairs[1], pairs[0]
        if len(pairs) > 3:
            pairs[2], pairs[3] = pairs[3], pairs[2]
        uv = [p for pair in pairs for p in pair]
    elif how == "horizon":
        uv[0][1] = 0.5
    elif how == "poles":
        uv = [[p[0], 0.0 if i % 2 == 0 else 1.0] for i, p in enumerate(uv)]
    elif how == "z_swap":
        z0, z1 = z1, z0
    elif how == "z_zero":
        z0 = 0.0
    elif how == "many":
        u = np.linspace(0, 1, 1000, endpoint=False)
        uv = [[float(x), v] for x in u for v in (0.3, 0.7)]
    elif how == "tiny_room":
        uv = [[0.5 + 1e-9 * i, v] for i in range(4) for v in (0.3, 0.7)]
    elif how == "wrap":
        uv = [[x, v] for x in (0.999, 0.0, 0.001, 0.002) for v in (0.3, 0.7)]
    elif how == "shuffle":
        uv = [p for pair in pairs[1::2] + pairs[0::2] for p in pair]
    return uv, z0, z1


def layout_bytes(sb, ext: str, spec) -> bytes:
    kind = spec[0]
    if ext == ".npy":
        valid = fill_array((2, W), "float64", "valid", "layout")
        if kind == "array":
            shape, dtype, fill = spec[1:]
            return npy_bytes(fill_array(shape, dtype, fill, "layout"))
        return special_npy(spec[1], valid)
    if kind == "raw":
        return spec[1].encode()
    if kind == "raw_bytes":
        return spec[1]
    if kind == "deep":
        return ('{"uv": ' + json_dumps_deep(deep(spec[1])) + "}").encode()
    if ext == ".txt":
        if kind == "lines":
            return "\n".join(spec[1]).encode("utf-8", "surrogatepass")
        uv, _, _ = perturb(*base_corners(sb), spec[1])
        return "\n".join(f"{u * W - 0.5:.3f} {v * H - 0.5:.3f}" for u, v in uv).encode()
    if kind == "uv":
        obj = {"uv": spec[1]}
        if spec[2] is not None:
            obj["z0"] = spec[2]
        if spec[3] is not None:
            obj["z1"] = spec[3]
        return json.dumps(obj).encode()
    if kind == "value":
        return json.dumps(spec[1]).encode()
    if kind == "perturb":
        uv, z0, z1 = perturb(*base_corners(sb), spec[1])
        return json.dumps({"uv": uv, "z0": z0, "z1": z1}).encode()
    raise AssertionError(spec)


def place_supplied(sb, field: str, folder: str, view: str, ext: str, raw: bytes, named: bool) -> None:
    """Write a supplied file for `view`: named by scene.json (`named`) or found by its stem."""
    data = sb.manifest()
    v = sb.view(data, view)
    old = v.pop(field, None)
    if old:
        (sb.scene / old).unlink(missing_ok=True)
    for stale in (sb.scene / folder).glob(f"{view}.*"):
        stale.unlink()
    name = f"{view}{ext}" if named or ext else f"{view}.bin"
    (sb.scene / folder).mkdir(exist_ok=True)
    (sb.scene / folder / name).write_bytes(raw)
    if named:
        v[field] = f"{folder}/{name}"
    sb.write_manifest(data)


@given(
    view=st.sampled_from(SCENE_VIEWS),
    file=layout_files,
    named=st.booleans(),
    until=st.sampled_from(["layout", "union", "sampling", "align"]),
)
@example(view="train_00", file=(".txt", ("lines", ["[/x] 1", "1 2"])), named=True, until="layout")
@example(view="train_01", file=(".npy", ("special", "pickle")), named=True, until="layout")
@example(view="train_01", file=(".npy", ("array", (2, 32), "float64", "nan")), named=False, until="layout")
@example(view="train_02", file=(".json", ("perturb", "self_intersect")), named=True, until="align")
@example(view="train_00", file=(".json", ("deep", 100_000)), named=True, until="layout")
@example(view="train_00", file=(".json", ("raw_bytes", b'{"uv": "\xc3("}')), named=True, until="layout")
@fuzz_settings(max_examples=40)
def test_layout_mutations(view, file, named, until, fuzz_base, tmp_path, capfd):
    ext, spec = file
    with sandbox(fuzz_base, tmp_path) as sb:
        place_supplied(sb, "layout", "layout", view, ext, layout_bytes(sb, ext, spec), named)
        run_example(sb, run_args(until), capfd, (view, file, named, until), "layouts")


# ----------------------------------------------------------------------------- depth
DEPTH_SHAPES = [(16, 32), (8, 16), (32, 64), (16, 33), (10, 10), (1, 2), (2, 4), (3, 6), (4, 8),
                (16, 32, 1), (16, 32, 3), (16, 32, 4), (32, 16), (0, 0), (2, 16, 32)]

depth_png = st.one_of(
    st.tuples(st.just("array"), st.sampled_from([s for s in DEPTH_SHAPES if len(s) == 2 or s[-1] in (1, 3, 4)]),
              st.sampled_from(["uint16", "uint8", "float32"]), st.sampled_from(["mm", "zero", "max", "random"])),
    st.tuples(st.just("raw_bytes"), st.sampled_from([b"", b"\x89PNG\r\n\x1a\n", b"not a png", b"\x00" * 64])),
    st.tuples(st.just("truncate"), st.floats(0.0, 1.0)),
    st.tuples(st.just("bomb"), st.sampled_from([(12000, 6000), (2 ** 31 - 1, 1)])),
)
depth_npy = st.one_of(
    st.tuples(st.just("array"), st.sampled_from(DEPTH_SHAPES), dtypes, fills),
    st.tuples(st.just("special"), npy_specials),
)
depth_files = st.one_of(
    st.tuples(st.just(".png"), depth_png),
    st.tuples(st.just(".npy"), depth_npy),
    st.tuples(st.sampled_from([".PNG", ".NPY", ".exr", ".tiff", ""]), st.just(("raw_bytes", b"\x00" * 8))),
)


def depth_bytes(sb, ext: str, spec) -> bytes:
    kind = spec[0]
    if kind == "raw_bytes":
        return spec[1]
    if kind == "truncate":
        raw = (sb.scene / "depth" / "train_00.png").read_bytes()
        return raw[: int(len(raw) * spec[1])]
    if kind == "bomb":
        return png_bomb(*spec[1])
    if ext == ".png":
        shape, dtype, fill = spec[1:]
        rng = np.random.default_rng(2)
        top = {"uint16": 65535, "uint8": 255, "float32": 1e6}[dtype]
        values = {"mm": rng.uniform(1000, 5000, shape), "zero": np.zeros(shape), "max": np.full(shape, top),
                  "random": rng.uniform(0, top, shape)}[fill]
        try:
            ok, buf = cv2.imencode(".png", values.astype(dtype))
        except cv2.error:
            ok, buf = False, None
        return buf.tobytes() if ok else values.astype(dtype).tobytes()
    if kind == "array":
        shape, dtype, fill = spec[1:]
        return npy_bytes(fill_array(shape, dtype, fill, "depth"))
    return special_npy(spec[1], fill_array((H, W), "float32", "valid", "depth"))


@given(
    view=st.sampled_from(SCENE_VIEWS),
    file=depth_files,
    named=st.booleans(),
    until=st.sampled_from(["depth", "align"]),
)
@example(view="train_00", file=(".npy", ("special", "pickle")), named=True, until="align")
@example(view="train_01", file=(".npy", ("array", (16, 32), "float32", "neg")), named=True, until="align")
@example(view="train_02", file=(".npy", ("array", (16, 32), "float64", "nan")), named=False, until="align")
@example(view="train_00", file=(".png", ("array", (16, 32), "uint8", "mm")), named=True, until="depth")
@example(view="train_00", file=(".png", ("array", (10, 10), "uint16", "mm")), named=True, until="depth")
@example(view="train_01", file=(".npy", ("special", "claims_huge")), named=True, until="depth")
@fuzz_settings(max_examples=30)
def test_depth_mutations(view, file, named, until, fuzz_base, tmp_path, capfd):
    ext, spec = file
    with sandbox(fuzz_base, tmp_path) as sb:
        place_supplied(sb, "depth", "depth", view, ext, depth_bytes(sb, ext, spec), named)
        run_example(sb, run_args(until), capfd, (view, file, named, until), "depth")
