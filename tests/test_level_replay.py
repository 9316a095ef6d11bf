"""Prioritised replay of training falls (train.level_replay): scores, the buffer's rules, the env's replays."""

from __future__ import annotations

import pytest
import torch
from torchrl.envs.utils import check_env_specs

from fallkit.config import EnvConfig, LevelReplayConfig, RewardConfig
from fallkit.env.fall_env import FallEnv
from fallkit.env.samplers.replay import LevelReplay
from fallkit.poses.end_pose_set import random_end_poses
from fallkit.sim import make_sim

NQ, NV = 3, 2


def falls(n: int, start: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """n distinguishable falls: qpos rows start, start+1, …; end poses their index."""
    q = (start + torch.arange(n, dtype=torch.float64)).view(-1, 1).expand(n, NQ).clone()
    return q, q[:, :NV].clone() * 10, torch.arange(n) + int(start)


def play(replay: LevelReplay, worlds: list[int], advantage: list[float], start: float, gen: torch.Generator):
    """Worlds restart (their earlier plays end), then one batch whose steps all belong to the new plays."""
    ids = torch.tensor(worlds)
    out = replay.restart(ids, *falls(len(worlds), start), gen)
    n = replay.play.numel()
    adv = torch.zeros(n, 2)
    adv[ids] = torch.tensor(advantage).view(-1, 1)
    replay.record(replay.fall_id.view(-1, 1).expand(n, 2), adv)
    return out


def test_a_play_is_scored_by_its_mean_absolute_advantage_once_its_last_steps_are_recorded():
    replay, gen = LevelReplay(LevelReplayConfig(share=0.5, size=8), 2, NQ, NV, "cpu"), torch.Generator()
    play(replay, [0, 1], [1.0, -3.0], 0, gen)
    assert replay.filled == 0  # both still playing
    # world 0 restarts within the next batch: its first step is the old play's, the second the new play's
    old = replay.fall_id.clone()
    replay.restart(torch.tensor([0]), *falls(1, 100), gen)
    ids = torch.stack([old, replay.fall_id], 1)
    replay.record(ids, torch.tensor([[-5.0, 7.0], [1.0, 1.0]]))
    assert replay.filled == 1
    assert replay.score[0] == pytest.approx((2 * 1.0 + 5.0) / 3)  # two steps of 1, the last of |-5|
    assert torch.equal(replay.qpos[0], falls(1, 0)[0][0]) and replay.pose[0] == 0


def test_fresh_falls_join_a_full_buffer_only_in_place_of_a_lower_scored_free_one():
    replay, gen = LevelReplay(LevelReplayConfig(share=0.0, size=2), 2, NQ, NV, "cpu"), torch.Generator()
    play(replay, [0, 1], [2.0, 4.0], 0, gen)
    play(replay, [0, 1], [1.0, 3.0], 10, gen)  # scores 2 and 4 stored: full
    assert replay.filled == 2 and sorted(replay.score.tolist()) == [2.0, 4.0]
    play(replay, [0, 1], [0.0, 0.0], 20, gen)  # 1 is below both, 3 replaces 2
    assert sorted(replay.score.tolist()) == [3.0, 4.0]
    assert sorted(replay.pose.tolist()) == [1, 11]


def test_replays_take_the_best_free_falls_each_in_one_world_at_a_time():
    cfg = LevelReplayConfig(share=0.99, size=4, temperature=0.01, staleness=0.0)
    replay, gen = LevelReplay(cfg, 4, NQ, NV, "cpu"), torch.Generator().manual_seed(0)
    play(replay, [0, 1, 2, 3], [1.0, 2.0, 3.0, 4.0], 0, gen)
    qpos, qvel, poses = play(replay, [0, 1, 2, 3], [0.0] * 4, 10, gen)  # the first four are scored and stored
    assert replay.filled == 4 and (replay.slot < 0).all()  # a fall replays only once the buffer is full
    qpos, qvel, poses = replay.restart(torch.tensor([0, 1]), *falls(2, 20), gen)
    # the two best (4.0 and 3.0: poses 3 and 2), distinct, now busy; the stored falls' own states
    assert sorted(poses.tolist()) == [2, 3] and sorted(qpos[:, 0].tolist()) == [2.0, 3.0]
    assert torch.equal(qvel, qpos[:, :NV] * 10)
    assert replay.busy.sum() == 2 and replay.stats()["level_replay/replayed"] == pytest.approx(2 / 10)
    qpos, _, poses = replay.restart(torch.tensor([2, 3]), *falls(2, 30), gen)
    assert sorted(poses.tolist()) == [0, 1]  # the best two are busy: the next two
    qpos, _, poses = replay.restart(torch.tensor([0]), *falls(1, 40), gen)
    assert poses.tolist() == [40]  # none free (world 0's play ended but is not scored yet): a fresh fall


def test_a_replay_is_rescored_by_its_new_play_and_staleness_reaches_the_lowest():
    cfg = LevelReplayConfig(share=0.99, size=2, temperature=0.01, staleness=1.0)
    replay, gen = LevelReplay(cfg, 1, NQ, NV, "cpu"), torch.Generator().manual_seed(0)
    for k, a in enumerate([5.0, 1.0, 2.0]):
        play(replay, [0], [a], 10 * k, gen)
    assert replay.pose.tolist() == [0, 10] and replay.score.tolist() == [5.0, 1.0]  # the third still plays
    # full: by staleness alone the fall stored longest ago replays; the third fall (2) takes the place of 1
    _, _, poses = play(replay, [0], [9.0], 30, gen)
    assert poses.tolist() == [0] and replay.pose.tolist() == [0, 20]
    play(replay, [0], [0.0], 40, gen)  # the replay ends: its new play's score replaces its old one
    assert replay.score.tolist() == [9.0, 2.0]


def test_the_env_starts_replayed_falls_exactly_and_tags_every_step(biped):
    poses = random_end_poses(biped, 16, torch.Generator().manual_seed(0))
    sim = make_sim(biped, 8, "mujoco", body_state=True)
    env = FallEnv(biped, EnvConfig(episode_length=0.1), RewardConfig(blend_time=0.1), poses, sim, seed=0)
    replay = env.replay_levels(LevelReplayConfig(share=0.5, size=8))
    td = env.reset()
    hold = env.action_for_setpoint(env.sim.state.joint_pos)
    steps = []
    for _ in range(40):  # 5-step episodes: 64 plays
        td["action"] = hold
        step, td = env.step_and_maybe_reset(td)
        steps.append(step)
        if len(steps) == 4:
            batch = torch.stack(steps, 1)
            assert batch["fall_id"].shape == (8, 4)
            replay.record(batch["fall_id"], batch["next", "reward"].squeeze(-1))
            steps = []
            stored = replay.slot >= 0
            for w in stored.nonzero().view(-1).tolist():  # a replaying world holds its stored fall's end pose
                assert env.end_pose_ids[w] == replay.pose[replay.slot[w]]
    assert replay.filled == 8 and 0.2 < replay.stats()["level_replay/replayed"] < 0.6
    # the simulator started each replay from the stored state: restart once more, compare before any step
    replay.config = LevelReplayConfig(share=0.99, size=8)
    env._restart(torch.ones(8, dtype=torch.bool), torch.arange(8))
    w = (replay.slot >= 0).nonzero().view(-1)
    assert w.numel() > 0
    assert torch.allclose(env.sim.state.qpos[w].double(), replay.qpos[replay.slot[w]])
    check_env_specs(env)  # "fall_id" is in the specs


def test_a_play_can_be_scored_by_one_reward_terms_advantage_and_a_wrong_term_is_one_line(tmp_path):
    from helpers import TINY, composed_config

    from fallkit.errors import ConfigError
    from fallkit.rl.trainer import Trainer

    replay = ["train.level_replay.share=0.5", "train.level_replay.size=4", "train.iterations=3"]
    trainer = Trainer(composed_config(*TINY, *replay, "train.level_replay.score=orientation"), tmp_path / "a")
    batch = trainer.collect()
    trainer.learn(batch)
    orientation = trainer.ppo.term_names.index("orientation")
    assert trainer.replay_column == orientation
    assert batch["term_advantages"].shape[-1] == len(trainer.ppo.term_names)
    assert trainer.replay.sum.abs().sum() > 0  # the column's |advantage| reached the plays
    with pytest.raises(ConfigError, match="level_replay.score=tilt is not a reward term"):
        Trainer(composed_config(*TINY, *replay, "train.level_replay.score=tilt"), tmp_path / "b")
    with pytest.raises(ConfigError, match="level_replay.score=tilt is not a reward term"):  # with the replay off too
        Trainer(composed_config(*TINY, "train.iterations=3", "train.level_replay.score=tilt"), tmp_path / "c")
