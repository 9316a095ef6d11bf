"""Per-episode domain randomisation (issue 14, B3): friction the critic sees, PD strength, action delay."""

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


def test_a_randomised_run_resumes_exactly(biped):
    a = _env(biped, RANDOM, seed=3)
    td = a.reset()
    g = torch.Generator().manual_seed(0)
    actions = [torch.randn(8, len(biped.joints), generator=g) * 0.3 for _ in range(6)]
    for act in actions[:3]:
        td = a.step_and_maybe_reset(td.set("action", act))[1]
    state = {k: (v.clone() if torch.is_tensor(v) else v) for k, v in a.run_state().items()}
    first = [a.step(td.set("action", act))["next", "critic"].clone() for act in actions[3:]]
    b = _env(biped, RANDOM, seed=99)
    b.reset()
    b.load_run_state(state)
    second = [b.step(td.set("action", act))["next", "critic"].clone() for act in actions[3:]]
    for x, y in zip(first, second):
        torch.testing.assert_close(x, y)
    torch.testing.assert_close(b.randomization.friction, a.randomization.friction)


def test_ranges_are_checked():
    with pytest.raises(ValueError, match="low 2.0 > high 1.0"):
        EnvConfig(randomization={"friction": {"enabled": True, "low": 2.0, "high": 1.0}})
