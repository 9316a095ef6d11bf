"""FallEnv: specs, rollouts, partial resets, goals in the path frame, config defaults."""

from __future__ import annotations

import math

import pytest
import torch
from helpers import host_reads
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs

from fallkit.config import BUILTIN_TERMS, EnvConfig, RewardConfig
from fallkit.env.fall_env import FallEnv
from fallkit.env.observations import actor_layout, critic_layout
from fallkit.env.samplers.initial_state import InitialStateSampler
from fallkit.poses.end_pose_set import random_end_poses
from fallkit.rotations import quat_from_euler, quat_mul, quat_rotate
from fallkit.sim import make_sim

N = 6
QUIET = EnvConfig(noise={"scale": 0.0}, disturbances={"enabled": False})


@pytest.fixture(scope="module")
def poses(biped):
    return random_end_poses(biped, 16, torch.Generator().manual_seed(0))


def make_env(spec, poses, n=N, env_cfg=None, reward_cfg=None, backend="mujoco", **sim_options):
    sim = make_sim(spec, n, backend, body_state=True, **sim_options)
    return FallEnv(spec, env_cfg or EnvConfig(), reward_cfg or RewardConfig(), poses, sim, seed=0)


@pytest.fixture(scope="module")
def env(biped, poses):
    return make_env(biped, poses)


def test_check_env_specs_and_layout(env, biped):
    check_env_specs(env, seed=0)
    assert env.batch_size == torch.Size([N])
    assert env.observation_spec["policy"].shape[-1] == sum(s for _, s in actor_layout(biped)) == 15 + 5 * 20
    assert env.observation_spec["critic"].shape[-1] == sum(s for _, s in critic_layout(biped))
    assert env.action_spec.shape == (N, 20)
    assert env.observation_spec["contact_force"].shape == (N, len(biped.components))


def test_step_and_maybe_reset_is_torchrls_to_the_bit_with_one_host_read(biped, poses):
    """FallEnv's own step_and_maybe_reset gives TorchRL's results (the default config: observation noise,
    disturbances) with one device-to-host read per step (the restarting worlds' ids) instead of ~6."""
    from torchrl.envs import EnvBase

    short = dict(env_cfg=EnvConfig(episode_length=0.2), reward_cfg=RewardConfig(blend_time=0.1))
    ours, torchrls = (make_env(biped, poses, **short) for _ in range(2))
    tds = [e.reset() for e in (ours, torchrls)]
    for e in (ours, torchrls):
        e.stagger_episodes()
    actions = torch.Generator().manual_seed(3)
    restarts, reads = 0, 0
    for _ in range(25):
        action = torch.randn(N, 20, generator=actions)
        stepped = []
        step = lambda: stepped.extend(ours.step_and_maybe_reset(tds[0].set("action", action.clone())))  # noqa: E731, B023
        reads += len(host_reads(step))
        a, a_next = stepped
        b, b_next = EnvBase.step_and_maybe_reset(torchrls, tds[1].set("action", action.clone()))
        assert (a == b).all() and (a_next == b_next).all() and set(a_next.keys()) == set(b_next.keys())
        restarts += int(a["next", "done"].sum())
        tds = [a_next, b_next]
    assert restarts >= N and reads <= 25


def test_rollout_truncates_at_t_and_resets_done_worlds(env, biped):
    td = env.reset()
    assert (env.step_count == 0).all()
    hold = env.action_for_setpoint(torch.as_tensor(biped.nominal_q(), dtype=torch.float32)).expand(N, -1)
    dones, forces = [], []
    for _ in range(env.max_steps + 2):
        td["action"] = hold.clone()
        td, td_next = env.step_and_maybe_reset(td)
        dones.append(td["next", "done"].clone())
        forces.append(td["next", "contact_force"])
        assert torch.isfinite(td["next", "reward"]).all() and torch.isfinite(td["next", "critic"]).all()
        td = td_next
    done = torch.stack(dones).squeeze(-1)  # [T, N]
    assert env.max_steps == round(3.0 / 0.02)
    assert not done[: env.max_steps - 1].any() and done[env.max_steps - 1].all() and not done[env.max_steps :].any()
    assert (env.step_count == 2).all()  # reset by the collector's "_reset" path, then stepped twice
    assert not td["terminated"].any()
    f = torch.stack(forces)
    assert (f >= 0).all() and (f[env.max_steps - 10 : env.max_steps].sum(-1) > 0).all()  # lying on the floor
    # a robot at rest on the floor carries its weight (16.2 kg) through its contacts
    total = f[env.max_steps - 10 : env.max_steps].sum(-1).mean()
    assert 0.5 * 16.2 * 9.81 < total < 3.0 * 16.2 * 9.81


def test_short_episodes_end_truncated_at_the_blend_time_and_resume_exactly(biped, poses):
    env = make_env(biped, poses, n=16)
    env.shorten_episodes(0.5)
    td = env.reset()
    env.stagger_episodes()
    assert (env.step_count < env.episode_steps).all()
    lengths = env.episode_steps.clone()
    assert set(lengths.tolist()) == {100, 150}  # T_blend = 2 s and T = 3 s at 50 Hz, both drawn
    starts = env.step_count.clone()
    hold = env.action_for_setpoint(env.sim.state.joint_pos)[:1].expand(16, -1).clone()
    seen = torch.zeros(16, dtype=torch.bool)
    for k in range(1, 151):
        td["action"] = hold
        step, td = env.step_and_maybe_reset(td)
        ended = starts + k == lengths
        # a world ends exactly at its own length, truncated (bootstrapped), never terminated
        assert torch.equal(step["next", "done"].view(-1), ended) and torch.equal(step["next", "truncated"].view(-1), ended)
        assert not step["next", "terminated"].any() and (env.step_count[ended] == 0).all()
        seen |= ended & (lengths == 100)
        lengths[ended], starts[ended] = env.episode_steps[ended], -k  # the next episode's own draw
    assert seen.any()  # short episodes did end early
    # an exact resume carries each world's length
    saved = env.run_state()
    other = make_env(biped, poses, n=16)
    other.shorten_episodes(0.5)
    other.load_run_state(saved)
    assert torch.equal(other.episode_steps, env.episode_steps)


def test_partial_reset_touches_only_masked_worlds(env):
    td = env.reset()
    for _ in range(5):
        td = env.rand_step(td)["next"]
    before_q = env.sim.state.qpos.clone()
    before_obs = td["policy"].clone()
    mask = torch.tensor([True, False, True, False, False, False]).view(N, 1)
    td["_reset"] = mask
    out = env.reset(td)
    m = mask.view(-1)
    assert (env.step_count[m] == 0).all() and (env.step_count[~m] == 5).all()
    assert torch.equal(env.sim.state.qpos[~m], before_q[~m])
    assert not torch.equal(env.sim.state.qpos[m], before_q[m])
    assert torch.equal(out["policy"][~m], before_obs[~m])
    assert not out["done"].any()


def test_reset_to_and_action_mapping(env, biped, poses):
    qpos, qvel = InitialStateSampler(biped).sample(N, torch.Generator().manual_seed(4))
    ids = torch.arange(N) % len(poses)
    td = env.reset_to(qpos, qvel, ids)
    torch.testing.assert_close(env.sim.state.qpos, qpos.float())
    assert torch.equal(env.end_pose_ids, ids)
    torch.testing.assert_close(env.goal_joint_pos, poses.joint_pos[ids])
    lay = env.sim.layout
    # the first actions "hold" the reset pose, as the simulator does after a reset
    torch.testing.assert_close(env.setpoint(env.last_action), qpos[:, lay.joint_qpos].float())
    q = torch.as_tensor(biped.joint_limits[:, 0] * 0.3 + biped.joint_limits[:, 1] * 0.7, dtype=torch.float32)
    torch.testing.assert_close(env.setpoint(env.action_for_setpoint(q).expand(N, -1)), q.expand(N, -1))
    assert td["policy"].shape == (N, env.observation_spec["policy"].shape[-1])
    with pytest.raises(ValueError, match="end_pose_ids must be in"):
        env.reset_to(qpos, qvel, ids + 100)


def test_observations_are_invariant_to_world_rotation_about_z(biped, poses):
    env = make_env(biped, poses, n=2, env_cfg=QUIET)
    qpos, qvel = InitialStateSampler(biped).sample(1, torch.Generator().manual_seed(7))
    qpos, qvel = qpos.repeat(2, 1), qvel.repeat(2, 1)
    # 1 m up: contact-free steps, so the physics itself is rotation-invariant (MuJoCo's
    # pyramidal friction cones are not: they are aligned with the world axes)
    qpos[:, 2] += 1.0
    yaw = torch.tensor([1.9], dtype=torch.float64)
    zero = torch.zeros(1, dtype=torch.float64)
    turn = quat_from_euler(zero, zero, yaw)
    # world 1: the same state turned by 1.9 rad about z and moved 3 m (positions, orientation, world velocity)
    qpos[1, :3] = quat_rotate(turn, qpos[1:2, :3])[0] + torch.tensor([3.0, -2.0, 0.0], dtype=torch.float64)
    qpos[1, 3:7] = quat_mul(turn, qpos[1:2, 3:7])[0]
    qvel[1, :3] = quat_rotate(turn, qvel[1:2, :3])[0]
    td = env.reset_to(qpos, qvel, torch.tensor([3, 3]))
    hold = env.last_action.clone()
    for k in range(3):
        for key, tol in (("policy", 1e-4), ("critic", 1e-3)):
            a, b = td[key][0], td[key][1]
            scale = a.abs().clamp(min=1.0)
            assert ((a - b).abs() / scale).max() < tol * (1 + 10 * k), (key, k)
        td = env.step(TensorDict({"action": hold}, batch_size=[2]))["next"]
    # the goal seen by the policy is the end pose's tilt: the same for both worlds
    assert torch.equal(env.goal_root_quat[0], env.goal_root_quat[1])


def test_offset_only_reward_is_one_per_step_and_unstable_worlds_truncate(biped, poses):
    only_offset = RewardConfig(**{t: 0.0 for t in BUILTIN_TERMS} | {"offset": 50.0})
    env = make_env(biped, poses, n=4, env_cfg=QUIET, reward_cfg=only_offset)
    td = env.rand_step(env.reset())
    torch.testing.assert_close(td["next", "reward"], torch.ones(4, 1))
    assert env.reward_terms_mean.keys() == {"offset"}
    # every world above 0.01 m/s counts as unstable: all truncate, no reward, and they are counted
    env = make_env(biped, poses, n=4, env_cfg=QUIET, reward_cfg=only_offset, max_speed=1e-3)
    td = env.rand_step(env.reset())
    assert td["next", "truncated"].all() and td["next", "done"].all() and not td["next", "terminated"].any()
    assert (td["next", "reward"] == 0).all() and env.num_unstable == 4


def test_disturbances_push_the_robot(biped, poses):
    strong = EnvConfig(
        noise={"scale": 0.0},
        disturbances={
            "roles": {"pelvis": {"force": 2000.0, "torque": 0.0, "on_time": (5.0, 5.0), "off_time": (0.02, 0.02)}}
        },
    )
    envs = [make_env(biped, poses, n=2, env_cfg=cfg) for cfg in (QUIET, strong)]
    qpos, qvel = InitialStateSampler(biped).sample(2, torch.Generator().manual_seed(9))
    qpos[:, 2] += 1.0  # in the air: only gravity and the disturbance act on the whole robot
    vel = []
    for env in envs:
        env.reset_to(qpos, qvel, torch.tensor([0, 1]))
        hold = env.last_action.clone()
        for _ in range(4):
            env.step(TensorDict({"action": hold}, batch_size=[2]))
        vel.append(env.sim.state.root_lin_vel.clone())
    assert envs[1].disturbances.active.all()
    # up to 2 kN per axis on 16 kg for 40–60 ms: metres per second of difference
    assert ((vel[1] - vel[0]).norm(dim=-1) > 0.5).all()


def test_noise_only_on_the_actor(env):
    td = env.reset()
    da = env.observation_spec["policy"].shape[-1]
    diff = td["policy"] - td["critic"][:, :da]
    assert diff[:, :-24].abs().max() > 0  # measured parts are noisy
    assert (diff[:, -24:] == 0).all()  # the goal is not


def test_config_errors_are_clear(biped, poses):
    # (that the composed config's defaults are the models' is tests/test_config.py)
    with pytest.raises(ValueError, match="blend_time"):
        FallEnv(biped, EnvConfig(episode_length=1.0), RewardConfig(), poses, make_sim(biped, 2, body_state=True))
    with pytest.raises(ValueError, match="body_state=True"):
        FallEnv(biped, EnvConfig(), RewardConfig(), poses, make_sim(biped, 2))
    with pytest.raises(ValueError, match="not a registered sampler"):
        EnvConfig(samplers={"initial_state": "nosuch"})
    assert math.isclose(EnvConfig().action_scale, 0.5)


@pytest.mark.slow
def test_warp_backend_specs_and_short_rollout(biped, poses):
    env = make_env(biped, poses, n=4, backend="warp", device="cpu")
    check_env_specs(env, seed=0)
    td = env.reset()
    for _ in range(10):
        td, td = env.step_and_maybe_reset(env.rand_action(td))
        assert torch.isfinite(td["policy"]).all() and torch.isfinite(td["critic"]).all()
    means = env.pop_reward_terms()
    assert set(means) == set(BUILTIN_TERMS) and all(math.isfinite(v) for v in means.values())


def test_path_frame_matches_the_rotation_helpers():
    from fallkit.env.observations import path_frame
    from fallkit.rotations import heading_quat, normalize, quat_rotate_inverse, tilt_quat

    q = normalize(torch.randn(500, 4, generator=torch.Generator().manual_seed(0)))
    q[0] = torch.tensor([0.0, 1.0, 0.0, 0.0])  # upside down: no heading
    frame = path_frame(q)
    torch.testing.assert_close(frame.tilt, tilt_quat(q))
    torch.testing.assert_close(frame.turn(frame.tilt), q)  # heading ⊗ tilt = q
    h = heading_quat(q)
    v = torch.randn(500, 7, 3)
    torch.testing.assert_close(frame.into(v), quat_rotate_inverse(h[:, None].expand(-1, 7, -1), v))


def test_observed_up_axes_are_what_the_orientation_reward_compares(biped, poses):
    """env.observe_gravity: the actor sees R(θ)ᵀe_z and R(θ̂)ᵀe_z, the orientation term is −u‖g − ĝ‖²
    of exactly those columns, and every column of the plain layout keeps its place."""
    from fallkit.env.observations import actor_slices
    from fallkit.rotations import gravity_in_frame

    only_orientation = RewardConfig(**{t: 0.0 for t in BUILTIN_TERMS} | {"orientation": 1.0})
    cfg = QUIET.model_copy(update={"observe_gravity": True})
    plain, up = (make_env(biped, poses, n=4, env_cfg=c, reward_cfg=only_orientation) for c in (QUIET, cfg))
    qpos, qvel = InitialStateSampler(biped).sample(4, torch.Generator().manual_seed(5))
    ids = torch.tensor([0, 3, 7, 11])
    tds = [env.reset_to(qpos, qvel, ids) for env in (plain, up)]
    cols = actor_slices(biped, gravity=True)
    assert env_width(plain) + 6 == env_width(up) and cols["blend"] == actor_slices(biped)["blend"]
    hold = up.last_action.clone()
    for _ in range(80):  # 1.6 s: u(t) > 0, the robots on the floor
        tds = [env.step(TensorDict({"action": hold}, batch_size=[4]))["next"] for env in (plain, up)]
    obs = tds[1]["policy"]
    torch.testing.assert_close(obs[:, : env_width(plain)], tds[0]["policy"])
    torch.testing.assert_close(obs[:, cols["gravity"]], gravity_in_frame(up.sim.state.root_quat), atol=1e-6, rtol=0)
    torch.testing.assert_close(obs[:, cols["goal_gravity"]], gravity_in_frame(poses.root_quat[ids].float()), atol=1e-6, rtol=0)
    distance = (obs[:, cols["gravity"]] - obs[:, cols["goal_gravity"]]).square().sum(-1)
    reward = tds[1]["reward"].view(-1)
    assert distance.min() > 0.01 and (reward < 0).all()
    torch.testing.assert_close(reward / distance, (reward / distance)[:1].expand(4), rtol=1e-4, atol=0)


def env_width(env) -> int:
    return env.observation_spec["policy"].shape[-1]
