"""L_orient (gaussians.losses.layout_orientation_loss): a layout Gaussian's shortest axis along its
plane normal, the official 360-GS code's `lambda_wscale` term, with the squared cosine."""

from __future__ import annotations

import math

import torch

from gaussians.densify import quat_to_rotmat
from gaussians.losses import layout_orientation_loss


def _axis_angle_quat(axis, angle: float) -> torch.Tensor:
    a = torch.tensor(axis, dtype=torch.float64)
    a = a / a.norm()
    return torch.cat([torch.tensor([math.cos(angle / 2)], dtype=torch.float64), math.sin(angle / 2) * a])


def test_flat_in_the_plane_is_zero_and_standing_up_is_one():
    rot = quat_to_rotmat(torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 3, dtype=torch.float64))
    log_scales = torch.log(torch.tensor([[1.0, 1.0, 0.1], [1.0, 1.0, 0.1], [0.1, 1.0, 1.0]], dtype=torch.float64))
    normals = torch.tensor([[0.0, 0.0, 2.0], [1.0, 0.0, 0.0], [-3.0, 0.0, 0.0]], dtype=torch.float64)
    per_row = [float(layout_orientation_loss(rot[i : i + 1], log_scales[i : i + 1], normals[i : i + 1]))
               for i in range(3)]
    assert per_row == [0.0, 1.0, 0.0]  # normal along z, across it, and along the shortest x axis (sign-free)
    assert float(layout_orientation_loss(rot, log_scales, normals)) == 1.0 / 3.0


def test_the_value_is_the_squared_sine_of_the_tilt():
    for angle in (0.1, 0.5, 1.0, math.pi / 2):
        q = _axis_angle_quat([1.0, 0.0, 0.0], angle)[None]
        rot = quat_to_rotmat(q)
        value = layout_orientation_loss(rot, torch.log(torch.tensor([[0.5, 0.4, 0.01]], dtype=torch.float64)),
                                        torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64))
        assert abs(float(value) - math.sin(angle) ** 2) < 1e-12


def test_its_gradient_lays_a_tilted_gaussian_flat():
    q = _axis_angle_quat([1.0, 1.0, 0.0], 0.7)[None].requires_grad_(True)
    log_scales = torch.log(torch.tensor([[0.5, 0.4, 0.01]], dtype=torch.float64))
    normal = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)
    opt = torch.optim.Adam([q], lr=0.02)
    start = float(layout_orientation_loss(quat_to_rotmat(q), log_scales, normal))
    for _ in range(300):
        opt.zero_grad()
        loss = layout_orientation_loss(quat_to_rotmat(q), log_scales, normal)
        loss.backward()
        opt.step()
    assert start > 0.3 and float(loss) < 1e-4


def test_degenerate_rows_stay_finite():
    """A zero normal, a zero quaternion (the identity) and tied scales: finite value and gradient."""
    q = torch.tensor([[0.0, 0.0, 0.0, 0.0], [1.0, 0.2, 0.0, 0.0]], dtype=torch.float64, requires_grad=True)
    log_scales = torch.zeros(2, 3, dtype=torch.float64)  # every axis the shortest: argmin picks one
    normals = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    value = layout_orientation_loss(quat_to_rotmat(q), log_scales, normals)
    value.backward()
    assert torch.isfinite(value) and torch.all(torch.isfinite(q.grad))
    empty = layout_orientation_loss(torch.zeros(0, 3, 3, requires_grad=True), torch.zeros(0, 3), torch.zeros(0, 3))
    assert float(empty) == 0.0 and empty.requires_grad


def test_training_with_the_term_lays_layout_gaussians_flatter(tiny_room):
    """Through the trainer (`lambda_layout_orient`, with `layout_reg`): the same run with the term
    ends with the layout Gaussians' shortest axes closer to their normals than without, and the
    other Gaussians are not what it measures."""
    from train_helpers import load_views, rooms, small_config

    from gaussians.init import random_points
    from gaussians.trainer import Trainer

    views = load_views(tiny_room)

    def run(weight: float) -> float:
        g = random_points(300, 2, rooms=rooms(tiny_room))
        g.is_layout[:150] = True
        g.normals[:150] = torch.tensor([0.0, 1.0, 0.0])
        g.log_scales[:150, 0] -= 1.5  # the shortest axis: local x, random rotations put it anywhere
        g.quats[:150] = torch.nn.functional.normalize(torch.randn(150, 4, generator=torch.Generator().manual_seed(0)))
        tr = Trainer(g, views, small_config(iterations=30, densify_from=100, lambda_layout=0.1, lr_rotation=0.03,
                                            lambda_layout_orient=weight))
        tr.train()
        lay = tr.g.is_layout
        return float(layout_orientation_loss(quat_to_rotmat(tr.g.quats[lay]), tr.g.log_scales[lay], tr.g.normals[lay]))

    off, on = run(0.0), run(1.0)
    assert on < 0.5 * off, (on, off)
