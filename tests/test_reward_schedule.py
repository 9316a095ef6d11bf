"""train.early_reward_factor: reward terms reweighted for a run's first env steps, the critic kept true at the switch."""

from __future__ import annotations

import csv

import pytest
import torch
from helpers import TINY, composed_config

from fallkit.config import ConfigError, RewardConfig
from fallkit.env.rewards import RewardSum
from fallkit.rl.models import ValueNet
from test_rewards import make_ctx, make_state

# 32 env steps an iteration: x5 for iterations 0-1, Table I's weight at once from iteration 2
EARLY = ["++train.early_reward_factor.orientation=5", "train.early_until_env_steps=64", "train.early_fade_env_steps=0"]


def test_reweight_multiplies_the_named_terms_and_restores_them():
    rewards = RewardSum(RewardConfig(), dt=0.02, components=["pelvis", "legs", "elbows", "shoulders", "head"])
    tilted = make_state(root_quat=torch.tensor([[0.0, 1.0, 0.0, 0.0]] * 2), joint_pos=torch.ones(2, 3))
    ctx = make_ctx(tilted)
    base = rewards.contributions(ctx)
    orientation = rewards.columns.index("orientation")
    assert base[:, orientation].abs().min() > 0  # upside down: the term is paid
    rewards.reweight({"orientation": 5.0})
    scaled = rewards.contributions(ctx)
    assert torch.allclose(scaled[:, orientation], 5.0 * base[:, orientation])
    others = [k for k in range(len(rewards.columns)) if k != orientation]
    assert torch.equal(scaled[:, others], base[:, others])
    rewards.reweight({})
    assert torch.equal(rewards.contributions(ctx), base)
    with pytest.raises(ValueError, match=r"orientaton is not a reward term of this run .* the terms: impact"):
        rewards.reweight({"orientaton": 5.0})


@pytest.mark.parametrize("normalize", [False, True], ids=["plain", "normalized-target"])
def test_scale_heads_scales_each_heads_prediction_exactly(normalize):
    torch.manual_seed(0)
    net = ValueNet(6, [8, 8], normalize_target=normalize, heads=3)
    obs = torch.randn(5, 6)
    if normalize:
        net.update_target_statistics(torch.randn(64, 3) * 7 - 20)
    before = net(obs)
    net.scale_heads(torch.tensor([1.0, 0.2, 3.0]))
    assert torch.allclose(net(obs), before * torch.tensor([1.0, 0.2, 3.0]), rtol=1e-5, atol=1e-5)


def test_the_factor_fades_linearly_to_table_ones_weight_with_the_head_kept_true():
    from fallkit.config import TrainConfig
    from fallkit.rl.reward_schedule import RewardSchedule

    torch.manual_seed(0)
    rewards = RewardSum(RewardConfig(), dt=0.02)
    config = TrainConfig(early_reward_factor={"orientation": 5}, early_until_env_steps=100, early_fade_env_steps=200)
    critic = ValueNet(4, [8], heads=len(rewards.names))
    schedule = RewardSchedule(config, rewards, critic, list(rewards.names))
    factor = [schedule.factors_at(s).get("orientation", 1.0) for s in (0, 99, 100, 200, 298, 300, 10**9)]
    assert factor == pytest.approx([5, 5, 5, 3, 1.04, 1, 1])
    obs = torch.randn(3, 4)
    schedule.start(0, per_iteration=50)
    before = critic(obs).detach()
    for steps in range(50, 400, 50):  # the fade in four steps, then Table I's weights
        logged = schedule.step(steps)
    orientation = rewards.names.index("orientation")
    assert logged == {"reward_factor/orientation": 1.0} and schedule.factors == {}
    assert torch.allclose(critic(obs).detach()[:, orientation], before[:, orientation] / 5, rtol=1e-5, atol=1e-6)
    assert rewards.scale[rewards.columns.index("orientation")].item() == pytest.approx(20 * 0.02)


def test_the_schedule_keeps_within_the_runs_budget_and_never_runs_back():
    """With a share of the budget spent, the position is at least that share of the schedule's length (until + fade):
    a run that ends before 300 env steps still ends at Table I's weights; a later, smaller reading does not undo it."""
    from fallkit.config import TrainConfig
    from fallkit.rl.reward_schedule import RewardSchedule

    rewards = RewardSum(RewardConfig(), dt=0.02)
    config = TrainConfig(early_reward_factor={"orientation": 5}, early_until_env_steps=100, early_fade_env_steps=200,
                         early_within_budget=True)  # fmt: skip
    critic = ValueNet(4, [8], heads=len(rewards.names))
    schedule = RewardSchedule(config, rewards, critic, list(rewards.names))
    schedule.start(0, per_iteration=50)
    assert schedule.step(50, budget_spent=0.5) == {"reward_factor/orientation": 4.0}  # at 150 of 300, not at 50
    assert schedule.position == 150
    assert schedule.step(60, budget_spent=0.1) == {"reward_factor/orientation": 4.0}  # never back
    assert schedule.step(200, budget_spent=0.5)["reward_factor/orientation"] == pytest.approx(3.0)  # env steps lead
    assert schedule.step(210, budget_spent=1.0) == {"reward_factor/orientation": 1.0} and schedule.factors == {}
    by_env_steps = RewardSchedule(config.model_copy(update={"early_within_budget": False}), rewards, critic,
                                  list(rewards.names))  # fmt: skip
    by_env_steps.start(0, per_iteration=50)
    assert by_env_steps.step(50, budget_spent=0.9) == {"reward_factor/orientation": 5.0}


def test_a_run_shorter_than_the_schedule_fades_within_its_iterations(tmp_path):
    """4 iterations of 32 env steps against a schedule of 64 + 256: the position is the larger of the env steps and
    the budget's share of 320 (0, 80, 160, 240 before each iteration), and the checkpoint keeps it for a resume."""
    from fallkit.rl.checkpoint import load_checkpoint
    from fallkit.rl.trainer import Trainer

    config = ["train.iterations=4", "++train.early_reward_factor.orientation=5", "train.early_until_env_steps=64",
              "train.early_fade_env_steps=256", "train.early_within_budget=true"]  # fmt: skip
    last = Trainer(composed_config(*TINY, *config), tmp_path / "run").run()
    rows = list(csv.DictReader((tmp_path / "run" / "metrics.csv").open()))
    assert [float(r["reward_factor/orientation"]) for r in rows] == pytest.approx([5.0, 4.75, 3.5, 2.25])
    assert load_checkpoint(last)["reward_schedule_position"] == 240
    # the default: by env steps alone, x5 until 64
    Trainer(composed_config(*TINY, *config[:-1]), tmp_path / "by_env_steps").run()
    rows = list(csv.DictReader((tmp_path / "by_env_steps" / "metrics.csv").open()))
    assert [float(r["reward_factor/orientation"]) for r in rows] == pytest.approx([5.0, 5.0, 5.0, 4.5])


def test_the_weights_switch_at_their_env_steps_with_the_critic_rescaled(tmp_path):
    """Iterations 0-1 collect with the orientation weight ×5, 2-3 with Table I's (logged as reward_factor/orientation);
    at the switch the orientation head's predictions fall by 5, the other heads' stay."""
    from fallkit.rl.models import value_net
    from fallkit.rl.trainer import Trainer

    # float32: bfloat16 products would round the two predictions differently
    trainer = Trainer(composed_config(*TINY, "train.iterations=4", "train.precision=float32", *EARLY), tmp_path / "run")
    rewards, critic = trainer.env.rewards, value_net(trainer.critic)
    orientation = rewards.names.index("orientation")
    table_one = rewards.weights[orientation].item() * rewards.dt
    column = rewards.columns.index("orientation")
    assert rewards.scale[column].item() == pytest.approx(5 * table_one)
    factors = [trainer.iterate()["reward_factor/orientation"] for _ in range(2)]
    with torch.no_grad():
        before = critic(trainer.td["critic"])
    trainer.reward_schedule.step(trainer.env_steps)  # 64 env steps: the switch
    with torch.no_grad():
        after = critic(trainer.td["critic"])
    assert rewards.scale[column].item() == pytest.approx(table_one)
    assert torch.allclose(after[..., orientation], before[..., orientation] / 5, rtol=1e-5, atol=1e-6)
    others = [k for k in range(after.shape[-1]) if k != orientation]
    assert torch.equal(after[..., others], before[..., others])
    trainer.run()  # iterations 2-3; the schedule's step at 64 is then a no-op
    rows = list(csv.DictReader((tmp_path / "run" / "metrics.csv").open()))
    assert factors == [5.0, 5.0] and [float(r["reward_factor/orientation"]) for r in rows] == [1.0, 1.0]


def test_a_factor_must_be_positive_and_name_a_reward_term(tmp_path):
    from fallkit.rl.trainer import Trainer

    with pytest.raises(ConfigError, match=r"train.early_reward_factor.orientation=0.0: a factor on a reward weight "
                                          r"must be > 0 \(to drop the term: reward.orientation=0"):  # fmt: skip
        composed_config(*TINY, "++train.early_reward_factor.orientation=0")
    with pytest.raises(ConfigError, match=r"train.early_reward_factor: joint is not a reward term of this run "
                                          r"\(terms: impact, .*joints"):  # fmt: skip
        Trainer(composed_config(*TINY, "++train.early_reward_factor.joint=5"), tmp_path / "run")
    with pytest.raises(ConfigError, match=r"train.self_imitation keeps returns under the reward weights they were "
                                          r"collected with, .* add train.early_reward_factor=null"):  # fmt: skip
        composed_config(*TINY, "train.self_imitation.steps=4")
    none = composed_config(*TINY, "++train.early_reward_factor.orientation=5", "train.early_reward_factor=null")
    assert none.train.early_reward_factor == {}


def test_a_checkpoint_inside_the_schedule_loads_a_critic_of_table_ones_weights(tmp_path):
    """Saved at a factor 5 (the checkpoint records it), the critic loads for evaluation in Table I's units (its
    orientation head ÷5), and a run started from it (train.init_from) scales it to its own first factor."""
    from fallkit.rl.checkpoint import load_checkpoint
    from fallkit.rl.models import value_net
    from fallkit.rl.policy import load_policy
    from fallkit.rl.trainer import Trainer

    config = ["train.iterations=1", "train.precision=float32", *EARLY]
    trainer = Trainer(composed_config(*TINY, *config), tmp_path / "run")
    last = trainer.run()
    orientation = trainer.env.rewards.names.index("orientation")
    assert load_checkpoint(last)["head_factors"][orientation] == 5.0
    obs = trainer.td["critic"]
    with torch.no_grad():
        trained = value_net(trainer.critic)(obs)
        loaded = load_policy(last).critic(obs)
        others = [k for k in range(trained.shape[-1]) if k != orientation]
        assert torch.allclose(loaded[..., orientation], trained[..., orientation] / 5, rtol=1e-5, atol=1e-6)
        assert torch.allclose(loaded[..., others], trained[..., others], rtol=1e-5, atol=1e-6)
        table_one = Trainer(composed_config(*TINY, "train.precision=float32", "train.early_reward_factor=null",
                                            f"train.init_from={last}"), tmp_path / "b")  # fmt: skip
        assert torch.allclose(value_net(table_one.critic)(obs), loaded, rtol=1e-5, atol=1e-6)
        again = Trainer(composed_config(*TINY, *config, f"train.init_from={last}"), tmp_path / "c")
        assert torch.allclose(value_net(again.critic)(obs), trained, rtol=1e-5, atol=1e-6)
