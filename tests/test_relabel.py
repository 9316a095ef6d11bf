"""Hindsight sensitivity weights (train.ppo.relabel_sensitivity): a collected fall, priced under other
weights, is the fall the simulator gives under those weights; PPO trains on both."""

from __future__ import annotations

import pytest
import torch
from helpers import TINY, composed_config

from fallkit.config import ConfigError, EnvConfig, RewardConfig
from fallkit.env.fall_env import FallEnv
from fallkit.env.observations import actor_slices
from fallkit.env.rewards.context import RewardSum
from fallkit.poses.end_pose_set import random_end_poses
from fallkit.rl.relabel import SensitivityRelabel
from fallkit.sim import make_sim

INPUTS = EnvConfig(noise={"scale": 0.0}, disturbances={"enabled": False}, sensitivity_inputs={"enabled": True})
ON = ["env.sensitivity_inputs.enabled=true", "train.ppo.relabel_sensitivity=true"]


def _held_fall(spec, sensitivity: torch.Tensor | None = None, steps: int = 40):
    """8 worlds (seed 0) falling for 0.8 s with their joints held, in one episode: the [8, steps] batch.
    `sensitivity` [8, C] replaces the drawn weights after the reset (the physics does not read them)."""
    poses = random_end_poses(spec, 16, torch.Generator().manual_seed(0))
    env = FallEnv(spec, INPUTS, RewardConfig(), poses, make_sim(spec, 8, "mujoco", body_state=True), seed=0)
    td = env.reset()
    if sensitivity is not None:
        env.sensitivity[:] = sensitivity
    hold = env.action_for_setpoint(env.sim.state.joint_pos.clone())
    return env, env.rollout(steps, lambda td: td.set("action", hold), auto_reset=False, tensordict=td)


def test_a_relabelled_fall_is_the_fall_the_simulator_gives_under_the_drawn_weights(biped):
    env, batch = _held_fall(biped)
    relabel = SensitivityRelabel(biped, INPUTS.sensitivity_inputs, env.rewards)
    image = relabel(batch, torch.Generator().manual_seed(1))
    cols = actor_slices(biped, sensitivity=True)["sensitivity"]
    drawn = image["policy"][:, 0, cols].exp()  # [8, C]: one draw per world for its whole rollout
    assert torch.equal(image["policy"][..., cols], drawn.log().unsqueeze(1).expand(-1, 40, -1))
    assert not torch.allclose(drawn, env.sensitivity)
    factor = drawn / torch.as_tensor(biped.sensitivity)
    assert factor.min() >= 0.2 - 1e-6 and factor.max() <= 5.0 + 1e-6  # drawn as the env draws them
    for key in ("policy", "critic", ("next", "critic")):  # only the weights' columns change
        other = torch.ones(image[key].shape[-1], dtype=torch.bool)
        other[cols] = False
        assert torch.equal(image[key][..., other], batch[key][..., other])
        assert torch.equal(image[key][..., cols], image["policy"][..., cols])
    assert torch.equal(image["action"], batch["action"])
    # the same fall with those weights from the start: the simulator's reward terms are the copy's
    _, replay = _held_fall(biped, sensitivity=drawn)
    terms = image["next", "reward_terms"]
    impact = terms[..., : len(biped.components)]
    assert impact.sum() < -1e-3 and not torch.allclose(impact, batch["next", "reward_terms"][..., : impact.shape[-1]])
    torch.testing.assert_close(terms, replay["next", "reward_terms"], rtol=1e-4, atol=1e-7)
    torch.testing.assert_close(image["next", "reward"], replay["next", "reward"], rtol=1e-4, atol=1e-6)
    assert image["next", "reward_terms"] is not batch["next", "reward_terms"]  # the batch itself is unchanged
    torch.testing.assert_close(batch["next", "reward_terms"].sum(-1, keepdim=True), batch["next", "reward"])


def test_relabelling_needs_drawn_weights_and_the_built_in_impact(biped):
    with pytest.raises(ConfigError, match="set env.sensitivity_inputs.enabled=true"):
        composed_config("train.ppo.relabel_sensitivity=true")
    with pytest.raises(ConfigError, match="with low < high"):
        composed_config(*ON, "env.sensitivity_inputs.low=1.0", "env.sensitivity_inputs.high=1.0")
    no_impact = RewardSum(RewardConfig(impact=0.0), 0.02, components=biped.component_names)
    with pytest.raises(ConfigError, match="has no such term"):
        SensitivityRelabel(biped, INPUTS.sensitivity_inputs, no_impact)


def test_training_relabels_every_minibatch_and_resumes(tmp_path):
    """Each minibatch holds the collected rows, then their relabelled copies (other weights and, chained into
    the same copy, other end poses), then (with the mirror) the mirror image of both: the loss's actor
    pass sees 4x the rows."""
    from fallkit.rl.ppo import policy_net
    from fallkit.rl.trainer import Trainer

    extra = ["train.ppo.mirror=true", "train.ppo.relabel_end_pose=true"]
    trainer = Trainer(composed_config(*TINY, *ON, *extra, "train.iterations=2"), tmp_path / "run")
    rows = []
    policy_net(trainer.ppo.loss.actor_network).register_forward_hook(lambda m, i, o: rows.append(o[0].shape[0]))
    last = trainer.run()
    mb = 8 * 4 // 2  # TINY: 8 envs x 4 steps in 2 minibatches
    assert set(rows) == {8, mb * 4}  # collection's 8 worlds; the loss's minibatches
    header, *lines = (tmp_path / "run" / "metrics.csv").read_text().splitlines()
    row = dict(zip(header.split(","), lines[-1].split(",")))
    assert 0.0 <= float(row["kl"]) < 1.0 and float(row["loss_critic"]) > 0.0 and float(row["mirror_loss"]) >= 0.0
    resumed = Trainer(composed_config(*TINY, *ON, *extra, "train.iterations=3", f"resume={last}"), tmp_path / "run2")
    assert len(resumed.ppo.relabels) == 2 and resumed.run().exists()


def test_the_copy_starts_at_ratio_one_and_its_advantage_carries_the_truncated_importance_weight(tmp_path):
    """The copy's old log-probability is the collecting policy's at the copy's observation (PPO's ratio 1
    before the first step), and its advantage is scaled by min(1, π_old(a|o') / π_old(a|o)): the copy
    no longer pulls π(·|o') toward the actions drawn at o (docs/sensitivity_inputs.md)."""
    from fallkit.rl.ppo import policy_net, value_net
    from fallkit.rl.relabel import RELABEL_MIN_WEIGHT, SILENT
    from fallkit.rl.trainer import Trainer

    trainer = Trainer(composed_config(*TINY, *ON), tmp_path / "run")
    with torch.no_grad():  # a policy whose actions depend on its inputs, its weights among them
        policy_net(trainer.actor).mean[-1].weight.normal_(0.0, 0.3)
    trainer.td = trainer._first_observation()
    batch = trainer.collect()
    ppo, keys = trainer.ppo, trainer.ppo.loss.tensor_keys
    plain = ppo.relabels[0](batch.clone(), torch.Generator().manual_seed(5))
    ppo.advantages(plain)
    _, image, _ = ppo._learning_samples(batch.clone(), value_net(trainer.critic), torch.Generator().manual_seed(5))
    with torch.no_grad():
        at_copy = trainer.actor.get_dist(plain.select("policy")).log_prob(plain[keys.action]).reshape(-1)
    weight = (at_copy - batch[keys.sample_log_prob].reshape(-1)).exp().clamp(max=1.0)
    assert weight.min() < 0.9  # the test means something: the policy reads its weights
    silent = weight < RELABEL_MIN_WEIGHT  # far off the collecting policy at o': no gradient (ratio e^-30)
    torch.testing.assert_close(image[keys.sample_log_prob], torch.where(silent, at_copy + SILENT, at_copy))
    weight = torch.where(silent, 0.0, weight)
    torch.testing.assert_close(image[keys.advantage].squeeze(-1), plain[keys.advantage].reshape(-1) * weight)


def test_a_fall_relabelled_with_another_end_pose_is_the_fall_the_simulator_gives_for_it(biped):
    """The copy under other end poses (train.ppo.relabel_end_pose): the goal's observation columns and the
    orientation and joint terms are the env's own for those end poses; everything else is the fall's."""
    from fallkit.rl.relabel import EndPoseRelabel

    env, batch = _held_fall(biped)
    tilt, joints = env.end_pose_goals()
    relabel = EndPoseRelabel(biped, tilt, joints, env.rewards, env.max_steps * env.dt, RewardConfig().blend_time,
                             sensitivity=True)  # fmt: skip
    image = relabel(batch, torch.Generator().manual_seed(3))
    cols = actor_slices(biped, sensitivity=True)
    goal = torch.zeros(image["policy"].shape[-1], dtype=torch.bool)
    goal[cols["goal_root_quat"]] = goal[cols["goal_joint_pos"]] = True
    ids = torch.randint(len(tilt), (8,), generator=torch.Generator().manual_seed(3))  # the copy's draw
    assert torch.equal(image["policy"][:, 0, cols["goal_joint_pos"]], joints[ids])
    assert not torch.equal(image["policy"][..., goal], batch["policy"][..., goal])
    for key in ("policy", "critic", ("next", "critic")):
        assert torch.equal(image[key][..., : len(goal)][..., ~goal], batch[key][..., : len(goal)][..., ~goal])
    # the same falls with those end poses set in the env: its reward terms and observed goals are the copy's
    poses = random_end_poses(biped, 16, torch.Generator().manual_seed(0))  # as _held_fall's env
    replay_env = FallEnv(biped, INPUTS, RewardConfig(), poses, make_sim(biped, 8, "mujoco", body_state=True), seed=0)
    td = replay_env.reset()
    replay_env.end_pose_ids[:] = ids
    replay_env.goal_root_quat[:] = tilt[ids]
    replay_env.goal_joint_pos[:] = joints[ids]
    td = replay_env._observation(td["done"])  # the first observation, now with the drawn goals
    hold = replay_env.action_for_setpoint(replay_env.sim.state.joint_pos.clone())
    replay = replay_env.rollout(40, lambda td: td.set("action", hold), auto_reset=False, tensordict=td)
    names = list(env.rewards.columns)
    tracking = [names.index("orientation"), names.index("joints")]
    assert image["next", "reward_terms"][..., tracking].abs().sum() > 0
    torch.testing.assert_close(image["next", "reward_terms"], replay["next", "reward_terms"], rtol=1e-4, atol=1e-7)
    torch.testing.assert_close(image["next", "reward"], replay["next", "reward"], rtol=1e-4, atol=1e-6)
    torch.testing.assert_close(image["critic"], replay["critic"])
