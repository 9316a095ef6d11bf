"""Potential-based orientation shaping (train.ppo.orientation_potential): what Φ reads, what GAE gets."""

from __future__ import annotations

import torch

from fallkit.config import BUILTIN_TERMS, EnvConfig, RewardConfig
from fallkit.env.fall_env import FallEnv
from fallkit.env.samplers.initial_state import InitialStateSampler
from fallkit.poses.end_pose_set import random_end_poses
from fallkit.rl.shaping import SHAPED_REWARD, OrientationPotential
from fallkit.sim import make_sim

QUIET = EnvConfig(noise={"scale": 0.0}, disturbances={"enabled": False})


def test_the_potential_is_the_distance_the_orientation_term_pays(biped):
    """Φ = −c‖g − ĝ‖² of the critic observation equals −c/dt × the orientation term's reward once u = 1:
    the shaping and the task measure the same tilt, in any world, mid-fall and on the floor."""
    poses = random_end_poses(biped, 16, torch.Generator().manual_seed(0))
    reward = RewardConfig(**{t: 0.0 for t in BUILTIN_TERMS} | {"orientation": 1.0, "blend_time": 0.02})
    env = FallEnv(biped, QUIET, reward, poses, make_sim(biped, 4, "mujoco", body_state=True), seed=0)
    qpos, qvel = InitialStateSampler(biped).sample(4, torch.Generator().manual_seed(5))
    td = env.reset_to(qpos, qvel, torch.tensor([0, 3, 7, 11]))
    potential = OrientationPotential(biped, scale=3.0)
    hold = env.last_action.clone()
    distances = []
    for _ in range(60):
        td = env.step(td.set("action", hold))["next"]
        d = -td["reward"] / env.dt  # u = 1 after the first step: the reward is −dt·‖g − ĝ‖²
        torch.testing.assert_close(potential(td["critic"]), -3.0 * d, atol=1e-5, rtol=1e-5)
        distances.append(d)
    assert torch.cat(distances).std() > 0.1  # the tilt changed over the fall: not a constant compared


def test_gae_reads_the_shaped_reward_and_the_task_reward_stays(biped):
    """shape(): ("next", shaped_reward) = r + γΦ(s') − Φ(s) with s' the state the step reached (the
    episode's last one at a truncation), so along an episode it sums to γ^T·Φ(s_T) − Φ(s_0) + Σγ^t r_t."""
    poses = random_end_poses(biped, 16, torch.Generator().manual_seed(0))
    env = FallEnv(biped, QUIET.model_copy(update={"episode_length": 0.4}), RewardConfig(blend_time=0.2), poses,
                  make_sim(biped, 3, "mujoco", body_state=True), seed=0)  # fmt: skip
    batch = env.rollout(30, break_when_any_done=False)  # 20 steps an episode: one truncation, one reset
    task = batch["next", "reward"].clone()
    potential, gamma = OrientationPotential(biped, scale=5.0), 0.99
    potential.shape(batch, gamma)
    torch.testing.assert_close(batch["next", "reward"], task)
    phi = potential(batch["critic"])
    shaped = batch["next", SHAPED_REWARD]
    discount = gamma ** torch.arange(20.0).view(1, -1, 1)
    first = ((shaped[:, :20] - task[:, :20]) * discount).sum(1)
    last_state = potential(batch["next", "critic"][:, 19])
    assert batch["next", "truncated"][:, 19].all() and not batch["next", "truncated"][:, :19].any()
    torch.testing.assert_close(first, gamma**20 * last_state - phi[:, 0], atol=1e-4, rtol=1e-5)
    assert not torch.allclose(batch["critic"][:, 20], batch["next", "critic"][:, 19])  # reset: a new fall


def test_training_with_shaping_gives_gae_the_shaped_reward(tmp_path):
    from helpers import TINY, composed_config

    from fallkit.rl.trainer import Trainer

    trainer = Trainer(composed_config(*TINY, "train.iterations=2", "train.ppo.orientation_potential=20"), tmp_path)
    assert trainer.ppo.gae.tensor_keys.reward == SHAPED_REWARD
    trainer.run()
    assert (tmp_path / "checkpoints" / "last.pt").exists()
