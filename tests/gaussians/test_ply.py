"""The standard 3DGS PLY: exact round trip, the original code's property order, other tools' files."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from gaussians import Gaussians, load_ply, save_ply
from gaussians.ply import ply_property_names


def random_gaussians(n: int = 50, degree: int = 3, seed: int = 0) -> Gaussians:
    gen = torch.Generator().manual_seed(seed)
    k = (degree + 1) ** 2

    def r(*shape):
        return torch.randn(*shape, generator=gen)

    return Gaussians(
        means=r(n, 3), quats=r(n, 4), log_scales=r(n, 3) - 3, opacity_logits=r(n), sh_dc=r(n, 1, 3),
        sh_rest=r(n, k - 1, 3), is_layout=torch.rand(n, generator=gen) > 0.5, normals=r(n, 3), u0=r(n, 3),
    )


def _header(path) -> list[str]:
    raw = path.read_bytes()
    return raw[: raw.index(b"end_header")].decode().splitlines()


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_round_trip_is_exact_with_extras(tmp_path, degree):
    g = random_gaussians(degree=degree)
    save_ply(tmp_path / "g.ply", g, extras=True)
    h = load_ply(tmp_path / "g.ply")
    assert h.sh_degree == degree
    for k, v in g.tensors().items():
        assert torch.equal(getattr(h, k), v), k


def test_standard_file_round_trips_the_render_parameters(tmp_path):
    g = random_gaussians()
    save_ply(tmp_path / "g.ply", g)
    h = load_ply(tmp_path / "g.ply")
    for k in ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest", "normals"):
        assert torch.equal(getattr(h, k), getattr(g, k)), k
    # without our extras: no layout flags, u0 = means
    assert not h.is_layout.any()
    assert torch.equal(h.u0, h.means)


def test_property_order_and_channel_major_f_rest(tmp_path):
    n, degree = 2, 3
    g = random_gaussians(n, degree)
    # sh_rest[i, j, c] = 100 c + j: channel-major means f_rest_{c*15 + j} = 100 c + j
    j = torch.arange(15, dtype=torch.float32)[None, :, None]
    c = torch.arange(3, dtype=torch.float32)[None, None, :]
    g.sh_rest = (100 * c + j).expand(n, 15, 3).clone()
    path = save_ply(tmp_path / "g.ply", g)
    lines = _header(path)
    assert lines[1] == "format binary_little_endian 1.0"
    assert lines[2] == f"element vertex {n}"
    names = [ln.split()[2] for ln in lines if ln.startswith("property")]
    assert all(ln.split()[1] == "float" for ln in lines if ln.startswith("property"))
    assert names[:9] == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    assert names[9:54] == [f"f_rest_{i}" for i in range(45)]
    assert names[54:] == ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    raw = path.read_bytes()
    body = np.frombuffer(raw[raw.index(b"end_header\n") + len(b"end_header\n"):], dtype="<f4").reshape(n, -1)
    f_rest = body[:, 9:54]
    for ch in range(3):
        np.testing.assert_array_equal(f_rest[0, ch * 15:(ch + 1) * 15], 100 * ch + np.arange(15))
    np.testing.assert_array_equal(body[:, 54], g.opacity_logits.numpy())
    np.testing.assert_array_equal(body[:, 55:58], g.log_scales.numpy())
    np.testing.assert_array_equal(body[:, 58:62], g.quats.numpy())


def test_reads_another_tools_file(tmp_path):
    """A PLY with extra properties, doubles, a comment and no normals (e.g. an exporter's)."""
    n = 3
    names = [nm for nm in ply_property_names(15) if nm not in ("nx", "ny", "nz")] + ["extra"]
    rng = np.random.default_rng(1)
    vals = rng.normal(size=(n, len(names)))
    header = ["ply", "format binary_little_endian 1.0", "comment made elsewhere", f"element vertex {n}"]
    header += [f"property double {nm}" for nm in names] + ["end_header"]
    (tmp_path / "o.ply").write_bytes(("\n".join(header) + "\n").encode() + vals.astype("<f8").tobytes())
    g = load_ply(tmp_path / "o.ply")
    assert len(g) == n and g.sh_degree == 3
    np.testing.assert_allclose(g.means.numpy(), vals[:, :3], rtol=1e-6)
    col = {nm: i for i, nm in enumerate(names)}
    np.testing.assert_allclose(g.sh_rest[:, 0, 1].numpy(), vals[:, col["f_rest_15"]], rtol=1e-6)
    assert torch.equal(g.normals, torch.zeros(n, 3))


def test_malformed_files_raise_naming_the_file(tmp_path):
    (tmp_path / "a.ply").write_bytes(b"not a ply")
    with pytest.raises(ValueError, match="a.ply"):
        load_ply(tmp_path / "a.ply")
    g = random_gaussians(5)
    path = save_ply(tmp_path / "b.ply", g)
    path.write_bytes(path.read_bytes()[:-10])
    with pytest.raises(ValueError, match="truncated"):
        load_ply(path)
    hdr = b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float x\nend_header\n"
    (tmp_path / "c.ply").write_bytes(hdr + np.zeros(1, "<f4").tobytes())
    with pytest.raises(ValueError, match="missing properties"):
        load_ply(tmp_path / "c.ply")


def test_the_training_dilation_round_trips_as_a_comment(tmp_path):
    """Gaussians.eps2d other than 3DGS's 0.3 is a header comment that load_ply reads back (and that
    the render defaults to); 0.3 writes no comment; a bad value is an error naming the file."""
    from gaussians.model import render
    import splatting

    g = random_gaussians(20)
    g.eps2d = 0.1
    path = save_ply(tmp_path / "g.ply", g)
    assert "comment eps2d 0.1" in _header(path)
    h = load_ply(path)
    assert h.eps2d == 0.1 and h.detach().eps2d == 0.1 and h.index(torch.arange(3)).eps2d == 0.1
    cam, vm = splatting.EquirectCamera(8, 16), torch.eye(4)
    with torch.no_grad():
        assert torch.equal(render(h, vm, cam).image, render(h, vm, cam, eps2d=0.1).image)
        assert not torch.equal(render(h, vm, cam).image, render(h, vm, cam, eps2d=0.3).image)
    plain = save_ply(tmp_path / "p.ply", random_gaussians(20))
    assert not any(line.startswith("comment") for line in _header(plain))
    assert load_ply(plain).eps2d == 0.3
    for bad in (b"comment eps2d fast\n", b"comment eps2d -1\n", b"comment eps2d nan\n"):
        raw = plain.read_bytes().replace(b"element vertex", bad + b"element vertex", 1)
        (tmp_path / "bad.ply").write_bytes(raw)
        with pytest.raises(ValueError, match="bad.ply.*eps2d"):
            load_ply(tmp_path / "bad.ply")
