"""Per-episode domain randomisation (issue 14, B3): friction the critic sees, PD strength, action delay,
link masses, joint damping and armature."""

from __future__ import annotations

import math

import pytest
import torch

from fallkit.config import EnvConfig, RewardConfig
from fallkit.env.fall_env import FallEnv
from fallkit.env.observations import critic_layout
from fallkit.pose_format import root_quat_from_pitch_roll
from fallkit.poses.checker import PoseChecker
from fallkit.poses.end_pose_set import random_end_poses
from fallkit.sim import make_sim

RANDOM = {"friction": {"enabled": True, "low": 0.3, "high": 1.5}, "gain_scale": {"enabled": True, "low": 0.5, "high": 1.5},
          "action_delay": 0.5}  # fmt: skip
DYNAMICS = {"mass": {"enabled": True, "low": 0.7, "high": 1.3}, "joint_damping": {"enabled": True, "low": 0.5, "high": 2.0},
            "armature": {"enabled": True, "low": 0.8, "high": 1.2}}  # fmt: skip


def _env(spec, randomization: dict | None, n: int = 8, seed: int = 0) -> FallEnv:
    cfg = EnvConfig(noise={"scale": 0.0}, disturbances={"enabled": False}, randomization=randomization or {})
    poses = random_end_poses(spec, 8, torch.Generator().manual_seed(0))
    return FallEnv(spec, cfg, RewardConfig(), poses, make_sim(spec, n, "mujoco", body_state=True), seed=seed)


def test_friction_reaches_the_contacts(biped, backend):
    """Two worlds sliding on their backs at 1.5 m/s: the low-friction one slides farther."""
    sim = make_sim(biped, 2, backend)
    checker = PoseChecker(biped)
    quat = torch.tensor(root_quat_from_pitch_roll(-math.pi / 2, 0.0))[None].expand(2, 4)
    qpos, _ = checker.on_ground(quat, torch.tensor(biped.nominal_q())[None].expand(2, -1), 0.0)
    qvel = torch.zeros(2, checker.layout.nv, dtype=torch.float64)
    qvel[:, 0] = 1.5
    sim.set_friction(torch.tensor([0.1, 1.5]))
    sim.reset(torch.arange(2), qpos, qvel)
    start, hold = sim.state.root_pos[:, 0].clone(), sim.state.joint_pos.clone()
    for _ in range(25):
        state = sim.step(hold)
    slid = (state.root_pos[:, 0] - start).tolist()
    assert slid[0] > slid[1] + 0.1, slid


def test_randomised_episodes_draw_friction_gains_and_delay_and_the_critic_sees_friction(biped):
    env = _env(biped, RANDOM)
    td = env.reset()
    r = env.randomization
    assert ((r.friction >= 0.3) & (r.friction <= 1.5)).all() and r.friction.std() > 0.05
    assert ((r.gain_scale >= 0.5) & (r.gain_scale <= 1.5)).all() and r.gain_scale.std() > 0.05
    assert 0 < int(r.delayed.sum()) < 8
    start = sum(s for name, s in critic_layout(biped)[: [n for n, _ in critic_layout(biped)].index("friction")])
    torch.testing.assert_close(td["critic"][:, start : start + 1], r.friction)
    # a delayed world applies the previous action (the hold) first, so its joints move less toward a far action
    action = torch.full((8, len(biped.joints)), 1.5)
    moved = (env.step(td.set("action", action))["next", "policy"] - td["policy"]).abs().sum(-1)
    assert moved[r.delayed].mean() < moved[~r.delayed].mean()


def test_randomisation_is_off_by_default_and_in_evaluation(biped):
    assert not _env(biped, None).randomization.active
    from fallkit.config import FallkitConfig, RobotConfig
    from fallkit.eval.evaluate import eval_run_config

    config = FallkitConfig(robot=RobotConfig(name="biped20"), env={"randomization": RANDOM})
    assert not eval_run_config(config, None).env.randomization.friction.enabled
    assert eval_run_config(config, None).env.randomization.action_delay == 0
    config = FallkitConfig(robot=RobotConfig(name="biped20"), env={"randomization": DYNAMICS})
    assert not any(getattr(eval_run_config(config, None).env.randomization, n).enabled for n in DYNAMICS)


def _lying_on_the_back(biped, n: int):
    checker = PoseChecker(biped)
    quat = torch.tensor(root_quat_from_pitch_roll(-math.pi / 2, 0.0))[None].expand(n, 4)
    qpos, _ = checker.on_ground(quat, torch.tensor(biped.nominal_q())[None].expand(n, -1), 0.0)
    return qpos, torch.zeros(n, checker.layout.nv, dtype=torch.float64)


def test_masses_reach_the_dynamics(biped):
    """Robots lying still carry their own weight: half and double the masses, half and double the force."""
    sim = make_sim(biped, 3, "mujoco")
    qpos, qvel = _lying_on_the_back(biped, 3)
    nbody = sim.model.nbody
    sim.set_mass_scale(torch.arange(3), torch.tensor([0.5, 1.0, 2.0])[:, None].expand(3, nbody))
    sim.reset(torch.arange(3), qpos, qvel)
    hold = sim.state.joint_pos.clone()
    for _ in range(100):  # 2 s: at rest
        state = sim.step(hold)
    weight = float(sim.model.body_mass.sum()) * 9.81
    force = state.contact_force[:, -1, :, 2].sum(-1)  # vertical, last substep, every component
    torch.testing.assert_close(force, torch.tensor([0.5, 1.0, 2.0]) * weight, rtol=0.03, atol=0.0)


def test_joint_damping_and_armature_reach_the_dynamics(biped):
    """Zero torque, arms swinging at 3 rad/s: more damping and more armature both slow them sooner."""
    sim = make_sim(biped, 3, "mujoco")
    qpos, qvel = _lying_on_the_back(biped, 3)
    arm = 6 + biped.joint_names.index("left_shoulder_pitch")  # dof index after the free joint
    qvel[:, arm] = 3.0
    sim.set_gain_scale(torch.zeros(3))
    sim.set_joint_scale(torch.arange(3), torch.tensor([1.0, 50.0, 1.0]), torch.tensor([1.0, 1.0, 40.0]))
    sim.reset(torch.arange(3), qpos, qvel)
    state = sim.step(sim.state.joint_pos.clone())
    change = (state.joint_vel[:, arm - 6] - 3.0).abs()  # after one policy step (20 ms)
    assert change[1] > 2.0 * change[0], change  # 50x the damping brakes the swing harder
    assert change[2] < 0.5 * change[0], change  # 40x the rotor inertia: every torque moves it less


def test_dynamics_randomisation_is_refused_on_warp():
    from helpers import composed_config

    from fallkit.config import ConfigError

    with pytest.raises(ConfigError, match="env.randomization.mass: randomised on sim=mujoco only so far"):
        composed_config("sim=warp", "env.randomization.mass.enabled=true")


def test_a_randomised_run_resumes_exactly(biped):
    a = _env(biped, {**RANDOM, **DYNAMICS}, seed=3)
    td = a.reset()
    g = torch.Generator().manual_seed(0)
    actions = [torch.randn(8, len(biped.joints), generator=g) * 0.3 for _ in range(6)]
    for act in actions[:3]:
        td = a.step_and_maybe_reset(td.set("action", act))[1]
    state = {k: (v.clone() if torch.is_tensor(v) else v) for k, v in a.run_state().items()}
    first = [a.step(td.set("action", act))["next", "critic"].clone() for act in actions[3:]]
    b = _env(biped, {**RANDOM, **DYNAMICS}, seed=99)
    b.reset()
    b.load_run_state(state)
    second = [b.step(td.set("action", act))["next", "critic"].clone() for act in actions[3:]]
    for x, y in zip(first, second):
        torch.testing.assert_close(x, y)
    torch.testing.assert_close(b.randomization.friction, a.randomization.friction)
    torch.testing.assert_close(b.randomization.mass_scale, a.randomization.mass_scale)
    assert a.randomization.mass_scale.std() > 0.05 and a.randomization.damping_scale.std() > 0.05


def test_ranges_are_checked():
    with pytest.raises(ValueError, match="low 2.0 > high 1.0"):
        EnvConfig(randomization={"friction": {"enabled": True, "low": 2.0, "high": 1.0}})
