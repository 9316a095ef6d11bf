"""Initial falling states (paper Sec. IV-D, Table II): ranges, order of rotations, rejection."""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest
import torch

from fallkit import registry
from fallkit.config import InitialStateConfig
from fallkit.env.samplers.initial_state import InitialStateSampler, InitialStateStock
from fallkit.poses.checker import PoseChecker
from fallkit.rotations import quat_from_euler, quat_mul, quat_rotate

N = 256


@pytest.fixture(scope="module")
def checker(biped):
    return PoseChecker(biped)


@pytest.fixture(scope="module")
def upright_yaw(biped, checker):
    """States without random heading, so pitch and roll can be read back."""
    sampler = InitialStateSampler(biped, InitialStateConfig(random_yaw=False), checker)
    return sampler.sample(N, torch.Generator().manual_seed(0))


def test_pitch_then_roll_within_30_degrees(biped, upright_yaw):
    qpos, _ = upright_yaw
    quat = qpos[:, 3:7]
    ez = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand(N, 3)
    z = quat_rotate(quat, ez)  # body z in the world: Rx(roll) Ry(pitch) e_z = (sin p, −sin r cos p, cos r cos p)
    pitch = torch.asin(z[:, 0])
    roll = torch.atan2(-z[:, 1], z[:, 2])
    zero = torch.zeros(N, dtype=torch.float64)
    # pitch applied first, then roll, both about world axes
    rebuilt = quat_mul(quat_from_euler(roll, zero, zero), quat_from_euler(zero, pitch, zero))
    torch.testing.assert_close(rebuilt * rebuilt[:, :1].sign(), quat * quat[:, :1].sign())
    limit = math.radians(30.0)
    for angle in (pitch, roll):
        assert angle.abs().max() <= limit + 1e-9
        assert angle.max() > 0.9 * limit and angle.min() < -0.9 * limit  # the whole range is used


def test_random_heading_keeps_the_tilt_range(biped, checker):
    qpos, _ = InitialStateSampler(biped, checker=checker).sample(64, torch.Generator().manual_seed(1))
    up = quat_rotate(qpos[:, 3:7], torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand(64, 3))
    assert (up[:, 2] >= math.cos(math.radians(30.0)) ** 2 - 1e-9).all()  # tilt <= acos(cos 30° cos 30°)
    x_axis = quat_rotate(qpos[:, 3:7], torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64).expand(64, 3))
    heading = torch.atan2(x_axis[:, 1], x_axis[:, 0])
    assert heading.max() - heading.min() > math.pi  # headings spread around the circle


def test_the_written_out_root_rotation_is_the_composed_one_to_the_bit():
    """`_root_quat` (the per-reset fast path) is Rz(yaw) ⊗ Rx(roll) ⊗ Ry(pitch) exactly as composed."""
    from fallkit.env.samplers.initial_state import _root_quat

    g = torch.Generator().manual_seed(2)
    roll, pitch, yaw = ((2.0 * torch.rand(4096, generator=g, dtype=torch.float64) - 1.0) * h for h in (0.6, 0.6, math.pi))
    zero = torch.zeros_like(yaw)
    composed = quat_mul(quat_from_euler(zero, zero, yaw), quat_mul(quat_from_euler(roll, zero, zero), quat_from_euler(zero, pitch, zero)))
    assert torch.equal(_root_quat(roll, pitch, yaw), composed)


def test_joint_positions_and_velocities_within_table_ii(biped, upright_yaw, checker):
    qpos, qvel = upright_yaw
    lay = checker.layout
    q = qpos[:, lay.joint_qpos]
    lim = torch.as_tensor(biped.joint_limits)
    assert ((q >= lim[:, 0]) & (q <= lim[:, 1])).all()
    v = lay.root_qvel
    for values, half in (
        (qvel[:, v : v + 3], 2.0),  # root linear, world frame [m/s]
        (qvel[:, v + 3 : v + 6], 0.5),  # root angular, root frame [rad/s]
        (qvel[:, lay.joint_qvel], 0.5),  # joints [rad/s]
    ):
        assert values.abs().max() <= half
        assert values.max() > 0.9 * half and values.min() < -0.9 * half


def test_no_self_collision_no_ground_penetration_lowest_geom_just_clears(biped, upright_yaw, checker):
    qpos, _ = upright_yaw
    colliding, lowest = checker.check(qpos)
    assert not colliding.any()
    clearance = InitialStateConfig().clearance
    torch.testing.assert_close(qpos[:, 2] + lowest, torch.full((N,), clearance, dtype=torch.float64))
    # in the scene with the floor: no contact at all (no penetration, no self-contact)
    m = biped.mj_model()
    d = mujoco.MjData(m)
    for row in qpos[:32].numpy():
        d.qpos[:] = row
        mujoco.mj_forward(m, d)
        assert d.ncon == 0
        # ...and it is the ground that is near: 1 cm lower and the robot touches it
        d.qpos[2] -= 2 * clearance
        mujoco.mj_forward(m, d)
        assert d.ncon > 0 and all(m.geom("floor").id in (c.geom1, c.geom2) for c in d.contact[: d.ncon])


def test_self_colliding_draws_are_rejected(biped, checker):
    g = torch.Generator().manual_seed(2)
    lim = torch.as_tensor(biped.joint_limits)
    raw = lim[:, 0] + (lim[:, 1] - lim[:, 0]) * torch.rand(512, len(lim), generator=g, dtype=torch.float64)
    lay = checker.layout
    root = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64).expand(512, 3)
    quat = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=torch.float64).expand(512, 4)
    colliding, _ = checker.check(lay.qpos(root, quat, raw))
    assert colliding.float().mean() > 0.05  # uniform draws self-collide (about 12 % for biped20)...
    kept = checker.sample_joints(512, g)
    colliding, _ = checker.check(lay.qpos(root, quat, kept))
    assert not colliding.any()  # ...and the sampler keeps none of them


def test_entry_point_and_seeding(biped):
    make = registry.load("fallkit.samplers", "initial_state")
    sampler = make(biped, roll_pitch_deg=10.0, joint_vel=0.0)
    assert sampler.config.roll_pitch_deg == 10.0
    a = sampler.sample(8, torch.Generator().manual_seed(5))
    b = sampler.sample(8, torch.Generator().manual_seed(5))
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])
    assert (a[1][:, sampler.layout.joint_qvel] == 0).all()
    up = quat_rotate(a[0][:, 3:7], torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand(8, 3))
    assert (up[:, 2] >= math.cos(math.radians(10.0)) ** 2 - 1e-9).all()
    assert np.isfinite(a[0].numpy()).all()


class _Counted:
    """The real sampler, counting its calls."""

    def __init__(self, sampler: InitialStateSampler):
        self.sampler, self.calls = sampler, []

    def sample(self, n: int, generator: torch.Generator):
        self.calls.append(n)
        return self.sampler.sample(n, generator)


def test_the_stock_hands_out_the_samplers_states_in_order_drawing_in_bulk(biped, checker):
    sampler = InitialStateSampler(biped, checker=checker)
    stock = InitialStateStock(counted := _Counted(sampler), chunk=64)
    g = torch.Generator().manual_seed(5)
    taken = [stock.take(n, g) for n in (3, 5, 1, 70, 2)]  # 81 states
    assert counted.calls == [64, 64]  # a draw only when the stock runs short, `chunk` at a time
    assert [len(q) for q, _ in taken] == [3, 5, 1, 70, 2]
    g = torch.Generator().manual_seed(5)
    direct = [sampler.sample(64, g) for _ in range(2)]
    qpos, qvel = torch.cat([q for q, _ in direct]), torch.cat([v for _, v in direct])
    assert torch.equal(torch.cat([q for q, _ in taken]), qpos[:81])
    assert torch.equal(torch.cat([v for _, v in taken]), qvel[:81])
    # what is left in stock is state: a stock loaded with it continues with the same states
    again = InitialStateStock(sampler, chunk=64)
    again.load(stock.state())
    assert torch.equal(again.take(47, torch.Generator())[0], qpos[81:])
    assert stock.take(200, g)[0].shape == (200, qpos.shape[1])  # more than a chunk at once: drawn as asked
