"""The example plugin's reward term and sampler, through fallkit's public API, on the real simulator."""

from __future__ import annotations

import math
from importlib.metadata import entry_points

import pytest
import torch

from fallkit.api import RewardContext, get_reward_term, get_robot, get_sampler, make_sim
from fallkit_example.rewards import root_spin
from fallkit_example.samplers import StandingPush, standing_push


@pytest.fixture(scope="module")
def biped():
    return get_robot("biped20")


def test_registered_by_this_distribution():
    for group, name, value in [
        ("fallkit.rewards", "root_spin", "fallkit_example.rewards:root_spin"),
        ("fallkit.samplers", "standing_push", "fallkit_example.samplers:standing_push"),
    ]:
        (ep,) = [ep for ep in entry_points(group=group) if ep.name == name]
        assert ep.dist.name == "fallkit-example" and ep.value == value
    assert get_reward_term("root_spin") is root_spin
    assert get_sampler("standing_push") is standing_push


def test_standing_push_starts_upright_on_the_floor_and_falls(biped):
    sampler = get_sampler("standing_push")(biped, roll_pitch_deg=5.0, root_lin_vel=1.5, joint_spread=1.0)
    assert isinstance(sampler, StandingPush)
    n = 16
    qpos, qvel = sampler.sample(n, torch.Generator().manual_seed(0))
    lay = sampler.layout
    assert qpos.shape == (n, biped.mj_model().nq) and qvel.shape == (n, biped.mj_model().nv)
    assert qpos.dtype == qvel.dtype == torch.float64
    # nominal joints, tilt within 5 degrees, lowest geom 5 mm above the floor, no self-contact
    assert torch.allclose(qpos[:, lay.joint_qpos], torch.as_tensor(biped.nominal_q()).expand(n, -1))
    quat = qpos[:, lay.root_qpos + 3 : lay.root_qpos + 7]
    up_z = 1 - 2 * (quat[:, 1] ** 2 + quat[:, 2] ** 2)  # z component of the root's up axis
    assert (up_z >= math.cos(math.radians(5.0 * math.sqrt(2))) - 1e-9).all()
    colliding, lowest = sampler.checker.check(qpos)
    assert not colliding.any()
    assert torch.allclose(qpos[:, lay.root_qpos + 2] + lowest, torch.full((n,), 0.005, dtype=torch.float64))
    push = qvel[:, lay.root_qvel : lay.root_qvel + 3]
    assert (push[:, 2] == 0).all() and (push[:, :2].norm(dim=-1) <= 1.5).all() and push.norm(dim=-1).max() > 0.5

    # limp (zero torque) from there: the robot falls, and the simulator stays stable
    sim = make_sim(biped, n, "mujoco", threads=1)
    sim.reset(torch.arange(n), qpos, qvel)
    sim.set_gain_scale(torch.zeros(n))
    for _ in range(75):  # 1.5 s
        state = sim.step(sim.state.joint_pos.clone())
    assert sim.num_unstable == 0
    assert (state.root_pos[:, 2] < qpos[:, 2] - 0.2).all()


def test_root_spin_penalizes_angular_velocity(biped):
    n = 3
    sim = make_sim(biped, n, "mujoco", threads=1)
    sampler = get_sampler("standing_push")(biped, roll_pitch_deg=0.0, root_lin_vel=0.0, root_ang_vel=0.0, joint_vel=0.0)
    qpos, qvel = sampler.sample(n, torch.Generator().manual_seed(0))
    spin = slice(sampler.layout.root_qvel + 3, sampler.layout.root_qvel + 6)  # root angular velocity, body frame
    qvel[1, spin] = torch.tensor([0.0, 2.0, 0.0], dtype=torch.float64)  # pitching
    qvel[2, spin] = torch.tensor([4.0, 0.0, 1.0], dtype=torch.float64)  # rolling fast
    sim.reset(torch.arange(n), qpos, qvel)
    state = sim.step(sim.state.joint_pos.clone())
    zeros = torch.zeros(n, len(biped.joints))
    ctx = RewardContext(
        state=state, action=zeros, last_action=zeros, last_last_action=zeros,
        target_root_quat=state.root_quat, target_joint_pos=state.joint_pos,
        sensitivity=torch.as_tensor(biped.sensitivity, dtype=torch.float32), time=torch.full((n,), biped.policy_dt),
        blend=torch.zeros(n), force_unit=1000.0, force_clip=10.0, dt=biped.policy_dt,
    )  # fmt: skip
    value = get_reward_term("root_spin")(ctx)
    assert value.shape == (n,)
    assert torch.allclose(value, -state.root_ang_vel.square().sum(-1))
    assert value[0] > -0.05 and value[2] < value[1] < value[0]  # standing still ≈ 0; more spin, more penalty
