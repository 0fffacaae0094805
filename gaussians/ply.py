"""The standard 3DGS PLY (the file the original code, SIBR, SuperSplat and gsplat read).

One `vertex` element, binary little-endian float32 properties in this order:
    x y z  nx ny nz  f_dc_0..2  f_rest_0..3(K-1)-1  opacity  scale_0..2  rot_0..3
opacity is the logit, scale_* the log of the standard deviations, rot_* the
(w, x, y, z) quaternion (not necessarily unit), f_dc_* the degree-0 SH
coefficient (colour = 0.5 + C0·f_dc) and f_rest channel-major as in the
original 3DGS (all red coefficients of bands 1..3, then green, then blue).
nx ny nz hold the layout plane normal (zero for non-layout Gaussians; the
original code writes zeros there and every viewer ignores them).

Axes: the project's world frame, OpenCV-style y down (x right, z forward),
metres — the same handedness and "y down" as the 3DGS outputs of COLMAP scenes,
so viewers that show those upright show ours upright too; a y-up viewer needs
a 180° rotation about x, i.e. (x, y, z) -> (x, -y, -z).

With `extras=True`, `u0_x u0_y u0_z is_layout` follow the standard properties
so a file round-trips every field of `Gaussians`; viewers that read by name
ignore them, but SIBR (which reads a fixed struct) does not, so the exported
point_cloud.ply is written without them.

A model fitted with a screen-space dilation other than 3DGS's 0.3 squared pixels
(`Gaussians.eps2d`, the train stage's `eps2d`) carries it as a header line
`comment eps2d 0.1`: our renders read it back, other tools skip comments.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import torch

from gaussians.model import DEFAULT_EPS2D, Gaussians
from runfs.errors import PanoError
from runfs.limits import check_ply_count

__all__ = ["save_ply", "load_ply", "ply_property_names", "nonfinite_problem"]

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_EXTRA_NAMES = ("u0_x", "u0_y", "u0_z", "is_layout")
#: header comment holding the model's screen-space dilation (Gaussians.eps2d) when it is not 0.3
_EPS2D_COMMENT = "eps2d"


def ply_property_names(num_rest: int, extras: bool = False) -> list[str]:
    """Vertex property names for `num_rest` = K-1 higher-order SH bases per channel."""
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(3 * num_rest)]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    if extras:
        names += list(_EXTRA_NAMES)
    return names


def nonfinite_problem(g: Gaussians) -> str | None:
    """How many Gaussians have a NaN or Inf parameter (of those a render reads), or None: a model
    that diverged is never written as a result, nor read as one (export, render, view, evaluate)."""
    n = len(g)
    params = (g.means, g.quats, g.log_scales, g.opacity_logits, g.sh_dc, g.sh_rest)
    ok = torch.ones(n, dtype=torch.bool, device=g.means.device)
    for t in params:
        ok &= torch.isfinite(t.detach().reshape(n, -1)).all(dim=1)
    bad = n - int(ok.sum())
    return f"{bad} of {n} Gaussians have NaN or Inf parameters" if bad else None


def save_ply(path: str | Path, g: Gaussians, extras: bool = False) -> Path:
    """Write `g` as a standard binary 3DGS PLY (see the module doc) straight to `path` (callers
    write a result through runfs.fsutil.atomic_write or a stage's temporary folder); returns the
    path. ValueError for a model with non-finite parameters."""
    path = Path(path)
    problem = nonfinite_problem(g)
    if problem:
        raise ValueError(f"{path}: not written: {problem} (a model that diverged)")
    path.parent.mkdir(parents=True, exist_ok=True)
    n = len(g)
    num_rest = g.sh_rest.shape[1]

    def f32(t: torch.Tensor) -> np.ndarray:
        return t.detach().to("cpu", torch.float32).numpy().reshape(n, -1)

    # [N, K-1, 3] -> [N, 3, K-1] -> flat: channel-major, as the original code writes.
    f_rest = f32(g.sh_rest.detach().transpose(1, 2).reshape(n, -1))
    cols = [f32(g.means), f32(g.normals), f32(g.sh_dc.reshape(n, 3)), f_rest,
            f32(g.opacity_logits.reshape(n, 1)), f32(g.log_scales), f32(g.quats)]
    if extras:
        cols += [f32(g.u0), g.is_layout.detach().cpu().numpy().astype(np.float32).reshape(n, 1)]
    data = np.ascontiguousarray(np.concatenate(cols, axis=1), dtype="<f4")
    names = ply_property_names(num_rest, extras)
    assert data.shape[1] == len(names)
    header = ["ply", "format binary_little_endian 1.0"]
    if g.eps2d != DEFAULT_EPS2D:  # a comment: other 3DGS tools skip it and draw with their 0.3
        header.append(f"comment {_EPS2D_COMMENT} {float(g.eps2d)!r}")
    header.append(f"element vertex {n}")
    header += [f"property float {name}" for name in names]
    header += ["end_header"]
    with open(path, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(data.tobytes())
    return path


def _parse_header(f, path: Path) -> tuple[str, int, list[tuple[str, str]], float]:
    first = f.readline().strip()
    if first != b"ply":
        raise ValueError(f"{path}: not a PLY file")
    fmt = None
    count = None
    props: list[tuple[str, str]] = []
    current = None
    eps2d = DEFAULT_EPS2D
    while True:
        line = f.readline()
        if not line:
            raise ValueError(f"{path}: PLY header has no end_header")
        tok = line.decode("ascii", "replace").split()
        if len(tok) == 3 and tok[:2] == ["comment", _EPS2D_COMMENT]:
            try:
                eps2d = float(tok[2])
            except ValueError:
                raise ValueError(f"{path}: PLY comment {_EPS2D_COMMENT} is not a number: {tok[2]!r}") from None
            if not (math.isfinite(eps2d) and eps2d >= 0):
                raise ValueError(f"{path}: PLY comment {_EPS2D_COMMENT} must be finite and >= 0, got {tok[2]}")
            continue
        if not tok or tok[0] in ("comment", "obj_info"):
            continue
        if tok[0] == "end_header":
            break
        if tok[0] == "format":
            fmt = tok[1]
        elif tok[0] == "element":
            current = tok[1]
            if current == "vertex":
                try:
                    count = int(tok[2])
                except (IndexError, ValueError):
                    raise ValueError(f"{path}: PLY element vertex has no count") from None
            elif count is None:
                raise ValueError(f"{path}: element {current!r} before vertex is not supported")
        elif tok[0] == "property" and current == "vertex":
            if tok[1] == "list":
                raise ValueError(f"{path}: list properties in the vertex element are not supported")
            if tok[1] not in _PLY_TYPES:
                raise ValueError(f"{path}: unknown PLY property type {tok[1]!r}")
            props.append((tok[2], _PLY_TYPES[tok[1]]))
    if fmt is None or count is None:
        raise ValueError(f"{path}: PLY header lacks a format or a vertex element")
    return fmt, count, props, eps2d


def load_ply(path: str | Path, dtype=torch.float32) -> Gaussians:
    """Read a standard 3DGS PLY (ours or another tool's) into `Gaussians`.

    Missing nx/ny/nz read as zero; without our extra properties u0 = means and
    is_layout = False. Raises ValueError naming the file on a malformed PLY.
    """
    path = Path(path)
    with open(path, "rb") as f:
        fmt, n, props, eps2d = _parse_header(f, path)
        data_bytes = os.fstat(f.fileno()).st_size - f.tell()
        record = sum(np.dtype(t).itemsize for _, t in props)
        try:  # the header's count against the file, before anything is allocated
            check_ply_count(path, n, record, data_bytes, ascii_values=len(props) if fmt == "ascii" else 0)
        except PanoError as e:
            raise ValueError(f"{path}: {e.problem}") from None
        if fmt == "ascii":
            arr = np.loadtxt(f, dtype=np.float64, max_rows=n, ndmin=2)
            if arr.shape != (n, len(props)):
                raise ValueError(f"{path}: expected {n}x{len(props)} ASCII values, got {list(arr.shape)}")
            cols = {name: arr[:, i] for i, (name, _) in enumerate(props)}
        else:
            endian = {"binary_little_endian": "<", "binary_big_endian": ">"}.get(fmt)
            if endian is None:
                raise ValueError(f"{path}: unknown PLY format {fmt!r}")
            dt = np.dtype([(name, endian + t) for name, t in props])
            raw = f.read(dt.itemsize * n)
            if len(raw) < dt.itemsize * n:
                raise ValueError(f"{path}: truncated ({len(raw)} of {dt.itemsize * n} vertex bytes)")
            rec = np.frombuffer(raw, dtype=dt, count=n)
            cols = {name: rec[name] for name, _ in props}

    def get(names: list[str]) -> np.ndarray:
        missing = [k for k in names if k not in cols]
        if missing:
            raise ValueError(f"{path}: not a 3DGS PLY, missing properties {missing[:4]}")
        return np.stack([np.asarray(cols[k], dtype=np.float32) for k in names], axis=1)

    def t(a: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(a)).to(dtype)

    means = get(["x", "y", "z"])
    n_rest = len([k for k in cols if k.startswith("f_rest_")])
    if n_rest % 3 != 0:
        raise ValueError(f"{path}: {n_rest} f_rest properties is not a multiple of 3")
    k = n_rest // 3 + 1
    if int(round(math.sqrt(k))) ** 2 != k or k > 16:
        raise ValueError(f"{path}: {n_rest} f_rest properties is not an SH degree 0..3")
    f_rest = get([f"f_rest_{i}" for i in range(n_rest)]) if n_rest else np.zeros((n, 0), np.float32)
    sh_rest = f_rest.reshape(n, 3, k - 1).transpose(0, 2, 1)
    normals = get(["nx", "ny", "nz"]) if all(c in cols for c in ("nx", "ny", "nz")) else np.zeros((n, 3), np.float32)
    if all(c in cols for c in _EXTRA_NAMES):
        u0 = get(list(_EXTRA_NAMES[:3]))
        is_layout = np.asarray(cols["is_layout"]) > 0.5
    else:
        u0 = means.copy()
        is_layout = np.zeros(n, bool)
    g = Gaussians(
        means=t(means),
        quats=t(get(["rot_0", "rot_1", "rot_2", "rot_3"])),
        log_scales=t(get(["scale_0", "scale_1", "scale_2"])),
        opacity_logits=t(get(["opacity"])[:, 0]),
        sh_dc=t(get(["f_dc_0", "f_dc_1", "f_dc_2"]).reshape(n, 1, 3)),
        sh_rest=t(sh_rest),
        is_layout=torch.from_numpy(np.ascontiguousarray(is_layout)),
        normals=t(normals),
        u0=t(u0),
        eps2d=eps2d,
    )
    problem = nonfinite_problem(g)
    if problem:
        raise ValueError(f"{path}: {problem}; a model that diverged cannot be used (train it again)")
    return g
