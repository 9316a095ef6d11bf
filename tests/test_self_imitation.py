"""train.self_imitation: the returns it stores, the steps it keeps, and that its update imitates them."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from fallkit.config import SelfImitationConfig
from fallkit.rl.models import make_actor, make_critic, value_net
from fallkit.rl.self_imitation import SelfImitation

OBS, ACT, GAMMA = 3, 2, 0.9


def nets(value: float):
    """A small actor, and a critic whose V(s) is `value` everywhere (its last layer zeroed, bias set)."""
    torch.manual_seed(0)
    actor, critic = make_actor(OBS, ACT, [8], 0.3), make_critic(OBS, [8])
    last = value_net(critic).value[-1]
    torch.nn.init.zeros_(last.weight)
    torch.nn.init.constant_(last.bias, value)
    return actor, critic


def batch(rewards: torch.Tensor, done: torch.Tensor) -> TensorDict:
    """A [N, T] batch of the keys the store reads: random observations and actions, given rewards and ends."""
    n, t = rewards.shape
    obs = torch.randn(n, t, OBS)
    return TensorDict(
        {
            "policy": obs, "critic": obs, "action": torch.randn(n, t, ACT),
            "next": {"reward": rewards.unsqueeze(-1), "done": done.unsqueeze(-1), "critic": torch.randn(n, t, OBS)},
        },
        batch_size=[n, t],
    )  # fmt: skip


def test_finished_episodes_store_their_discounted_returns_where_they_beat_the_value():
    v = -1.0
    actor, critic = nets(v)
    sil = SelfImitation(SelfImitationConfig(steps=1, size=32, minibatch=2), actor, critic, 2, 8, GAMMA)
    rewards = torch.tensor([[1.0, -2.0, 1.0, 5.0], [0.5, 0.5, 0.5, 0.5]])
    done = torch.tensor([[False, False, True, False], [False] * 4])
    sil.add(batch(rewards, done))
    # world 0's episode ended at its third step: R = r + γ·R', the tail bootstrapped by V = −1
    r2 = 1.0 + GAMMA * v
    r1 = -2.0 + GAMMA * r2
    r0 = 1.0 + GAMMA * r1
    kept = [r for r in (r0, r1, r2) if r > v]
    assert sil.stored == len(kept) == 2  # R_0 = −0.72 and R_2 = 0.1 do, R_1 = −1.91 does not beat V
    assert torch.allclose(sil.store["return"][:2], torch.tensor(kept))
    # world 1's episode runs on into the next batch; world 0's next episode started at its fourth step
    sil.add(batch(torch.zeros(2, 2), torch.tensor([[False, False], [True, False]])))
    world1 = [sum(0.5 * GAMMA ** (k - j) for k in range(j, 4)) + GAMMA ** (5 - j) * v for j in range(4)] + [GAMMA * v]
    assert sil.stored == 2 + sum(r > v for r in world1)
    assert torch.allclose(sil.store["return"][2 : sil.stored], torch.tensor([r for r in world1 if r > v]))
    assert sil.length.tolist() == [3, 1]


def test_its_update_raises_the_log_probability_of_the_stored_actions():
    actor, critic = nets(-10.0)  # every return beats it
    cfg = SelfImitationConfig(steps=20, size=64, minibatch=16, learning_rate=1e-2)
    sil = SelfImitation(cfg, actor, critic, 4, 16, GAMMA)
    sil.add(batch(torch.zeros(4, 16), torch.zeros(4, 16, dtype=torch.bool).index_fill_(1, torch.tensor([15]), True)))
    assert sil.stored == 64
    net = sil.net

    def log_prob() -> float:
        with torch.no_grad():
            loc, scale = net(sil.store["policy"])
            return torch.distributions.Normal(loc, scale).log_prob(sil.store["action"]).sum(-1).mean().item()

    before = log_prob()
    figures = sil.update(torch.Generator().manual_seed(0))
    assert log_prob() > before + 0.1
    assert figures["self_imitation/pulling"] == 1.0 and 0 < figures["self_imitation/weight"] <= cfg.max_weight


def test_one_terms_self_imitation_trains_and_a_wrong_term_is_one_line_even_when_off(tmp_path):
    from helpers import TINY, composed_config

    from fallkit.errors import ConfigError
    from fallkit.rl.trainer import Trainer

    term = ["train.early_reward_factor=null", "train.self_imitation.steps=2", "train.self_imitation.minibatch=2",
            "train.self_imitation.term=orientation"]  # fmt: skip
    trainer = Trainer(composed_config(*TINY, *term), tmp_path / "a")
    sil = trainer.self_imitation
    assert sil.head == trainer.ppo.term_names.index("orientation")
    assert [trainer.env.rewards.columns[c] for c in sil.columns.tolist()] == ["orientation"]
    for _ in range(4):  # episodes of 10 steps, 4 per iteration: finished falls reach the store
        stats = trainer.learn(trainer.collect())
    assert sil.stored > 0 and stats["self_imitation/loss"] != 0
    with pytest.raises(ConfigError, match="self_imitation.term=tilt is not a reward term"):
        Trainer(composed_config(*TINY, "train.self_imitation.term=tilt"), tmp_path / "b")


def test_min_weight_keeps_only_the_steps_that_beat_the_value_by_that_many_advantage_stds():
    actor, critic = nets(-1.0)
    sil = SelfImitation(SelfImitationConfig(steps=1, min_weight=1.0), actor, critic, 1, 8, GAMMA)
    b = batch(torch.tensor([[1.0, -2.0, 1.0]]), torch.tensor([[False, False, True]]))
    b["advantage"] = torch.tensor([[[-0.5], [0.5], [0.0]]])  # σ_A = 0.5: R must beat V = −1 by more than 0.5
    sil.add(b)
    # R_2 = 0.1 is kept; R_0 = −0.72 beat V, but not by enough
    assert torch.allclose(sil.store["return"][: sil.stored], torch.tensor([1.0 + GAMMA * -1.0]))
