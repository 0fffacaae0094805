"""The perspective rig of the 3D-GS baseline: crop geometry, the cubemap as its special case,
and the stitch that blends rendered crops back into a panorama."""

from __future__ import annotations

import math

import pytest
import torch

import splatting
from splatting.cameras import CUBEMAP_FACE_AXES
from splat_helpers import random_scene


def fibonacci_sphere(n: int) -> torch.Tensor:
    """n roughly uniform unit directions, plus the two poles exactly."""
    i = torch.arange(n, dtype=torch.float64) + 0.5
    y = 1 - 2 * i / n
    r = torch.sqrt(1 - y * y)
    a = math.pi * (3 - math.sqrt(5)) * i
    d = torch.stack([r * torch.cos(a), y, r * torch.sin(a)], -1)
    return torch.cat([d, torch.tensor([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0]], dtype=torch.float64)])


def in_crop(rig, dirs: torch.Tensor) -> torch.Tensor:
    """[P,K] whether each direction falls on each crop's image (pinhole frustum test)."""
    v = torch.einsum("kij,pj->pki", rig.rotations(), dirs)
    t = math.tan(math.radians(rig.fov_deg) / 2)
    z = v[..., 2]
    return (z > 0) & (v[..., 0].abs() <= t * z) & (v[..., 1].abs() <= t * z)


def test_paper_rig_is_eight_level_120_degree_crops_on_three_rings_covering_the_sphere():
    rig = splatting.crop_rig(64)  # the defaults are the paper's
    assert len(rig) == 8 and rig.fov_deg == 120.0
    cam = rig.camera
    assert (cam.width, cam.height) == (64, 64) and cam.fx == pytest.approx(32 / math.tan(math.radians(60)))
    R = rig.rotations()
    torch.testing.assert_close(R @ R.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(8, 3, 3))
    assert torch.allclose(torch.det(R), torch.ones(8, dtype=torch.float64))
    assert torch.allclose(R[:, 0, 1], torch.zeros(8, dtype=torch.float64))  # level: x axis horizontal
    # viewing directions: elevations -45 (2 crops), 0 (4), 45 (2); yaws evenly spread from 0
    z = R[:, 2]
    elev = torch.rad2deg(torch.asin(-z[:, 1]))
    yaw = torch.rad2deg(torch.atan2(z[:, 0], z[:, 2])) % 360
    torch.testing.assert_close(elev, torch.tensor([-45.0, -45, 0, 0, 0, 0, 45, 45], dtype=torch.float64))
    torch.testing.assert_close(yaw, torch.tensor([0.0, 180, 0, 90, 180, 270, 0, 180], dtype=torch.float64))
    assert rig.names[0] == "el-45_yaw0" and rig.names[-1] == "el+45_yaw180"
    # every direction, the poles included, is on at least one crop's image
    seen = in_crop(rig, fibonacci_sphere(20000))
    assert bool(seen.any(1).all())
    # ... and the 2 + 4 + 2 split is what makes it so: all eight on the horizon leave the poles unseen
    flat = splatting.crop_rig(64, 120.0, (0.0,), (8,))
    assert not bool(in_crop(flat, fibonacci_sphere(20000)).any(1).all())


def test_the_cubemap_is_the_rig_of_six_90_degree_faces():
    rig = splatting.crop_rig(16, 90.0, (0.0, 90.0, -90.0), (4, 1, 1))
    cube = splatting.cubemap_rig(16)
    assert cube.axes == rig.axes  # exact: multiples of 90° give exact axis permutations
    for name, axes in zip(cube.names, cube.axes):
        assert axes == CUBEMAP_FACE_AXES[name]
    assert cube.camera.fx == 8.0
    faces = splatting.cubemap_faces(16)
    assert [f[0][:3, :3].tolist() for f in faces] == [list(map(list, a)) for a in cube.axes]


def test_bad_rigs_are_refused():
    with pytest.raises(ValueError, match="one crop count per elevation"):
        splatting.crop_rig(16, 120.0, (0.0, 45.0), (4,))
    with pytest.raises(ValueError, match=r"\[-90, 90\]"):
        splatting.crop_rig(16, 120.0, (100.0,), (4,))
    with pytest.raises(ValueError, match="field of view"):
        splatting.crop_rig(16, 180.0)
    # four 60° crops on the horizon see a band only: the stitch refuses, naming the gap
    with pytest.raises(ValueError, match="leave .* panorama pixels unseen"):
        splatting.stitch_table(16, 32, splatting.crop_rig(16, 60.0, (0.0,), (4,)))


def smooth_crops(rig, fn):
    """Each crop's pixels coloured by fn(direction in the panorama frame)."""
    d = rig.camera.pixel_dirs(dtype=torch.float64)
    d = d / d.norm(dim=-1, keepdim=True)
    return torch.stack([fn(d @ R) for R in rig.rotations()])


def test_stitch_blends_to_a_partition_of_unity_and_recovers_a_smooth_panorama():
    H, W = 48, 96
    for rig in (splatting.crop_rig(48), splatting.cubemap_rig(24)):
        ones = torch.ones(len(rig), rig.size, rig.size, 1, dtype=torch.float64)
        torch.testing.assert_close(splatting.stitch(ones, H, W, rig), torch.ones(H, W, 1, dtype=torch.float64))

        def fn(d):  # a smooth colour of the direction
            return 0.5 + 0.4 * torch.stack([d[..., 0], d[..., 1] * d[..., 2], torch.sin(2 * d[..., 2])], -1)

        pano = splatting.stitch(smooth_crops(rig, fn), H, W, rig)
        expect = fn(splatting.EquirectCamera(H, W).pixel_dirs(dtype=torch.float64))
        assert float((pano - expect).abs().max()) < 0.01  # bilinear resampling error only (a wrong rotation: 0.8)
    # overlapping crops are cross-faded: where two crops disagree the stitch lies between them
    rig = splatting.crop_rig(32)
    crops = torch.arange(len(rig), dtype=torch.float64)[:, None, None, None].expand(-1, 32, 32, 1)
    pano = splatting.stitch(crops.contiguous(), H, W, rig)[..., 0]
    frac = pano - pano.floor()
    assert float((frac > 0.05).double().mean()) > 0.3  # a large part of the sphere is blended


@pytest.mark.parametrize("rig", [splatting.crop_rig(40), splatting.cubemap_rig(32)], ids=["paper-crops", "cubemap"])
def test_stitched_render_is_close_to_the_direct_render(rig):
    means, quats, scales, op, col = random_scene(40, seed=7, spread=1.0, scale=(0.1, 0.3), opacity=(0.5, 0.9))
    means = means / means.norm(dim=-1, keepdim=True) * 2.5
    H, W = 32, 64
    eye = torch.eye(4, dtype=means.dtype)
    direct = splatting.render(means, quats, scales, op, col, eye, splatting.EquirectCamera(H, W))
    params = [x.clone().requires_grad_(True) for x in (means, quats, scales, op, col)]
    out = splatting.render_stitched(*params, eye, H, W, rig)
    assert out.image.shape == (H, W, 3) and out.means2d.shape == (len(rig), 40, 2)
    mse = float(((out.image.detach() - direct.image) ** 2).mean())
    assert 10 * math.log10(1 / mse) > 25
    out.image.sum().backward()
    assert all(bool(torch.isfinite(p.grad).all()) for p in params)
