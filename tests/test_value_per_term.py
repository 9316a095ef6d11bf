"""A value head per reward term (train.ppo.value_per_term): what the env gives, what GAE makes of it."""

from __future__ import annotations

import pytest
import torch

from fallkit.config import EnvConfig, PPOConfig, RewardConfig
from fallkit.env.fall_env import FallEnv
from fallkit.poses.end_pose_set import random_end_poses
from fallkit.rl.models import make_actor, make_critic, value_net
from fallkit.rl.ppo import PPO
from fallkit.rl.shaping import OrientationPotential
from fallkit.sim import make_sim

QUIET = EnvConfig(noise={"scale": 0.0}, disturbances={"enabled": False}, episode_length=0.4)


def _rollout(biped, steps: int = 30):
    """Three worlds over 30 steps of 20-step episodes: every world truncates at step 20 and restarts."""
    poses = random_end_poses(biped, 16, torch.Generator().manual_seed(0))
    env = FallEnv(biped, QUIET, RewardConfig(blend_time=0.2), poses, make_sim(biped, 3, "mujoco", body_state=True))
    return env, env.rollout(steps, break_when_any_done=False)


def test_reward_terms_are_the_summands_of_the_reward_up_to_an_episodes_last_step(biped):
    env, batch = _rollout(biped)
    terms, reward = batch["next", "reward_terms"], batch["next", "reward"]
    columns = env.rewards.columns  # a column per term, the impact one per component
    assert columns == [f"impact/{c}" for c in biped.component_names] + env.rewards.names[1:]
    assert terms.shape == (3, 30, len(columns))
    torch.testing.assert_close(terms.sum(-1, keepdim=True), reward)
    assert batch["next", "truncated"][:, 19].all()
    # the step that ended an episode keeps its terms (the reset that followed did not zero them)
    offset = columns.index("offset")
    torch.testing.assert_close(terms[:, 19, offset], torch.full((3,), env.dt * 50.0))
    impact = terms[..., : len(biped.component_names)]
    assert (impact < 0).any() and (impact.sum((0, 1)) < 0).sum() >= 2  # a real fall, on more than one part
    assert torch.equal(batch["reward_terms"][:, 20], torch.zeros(3, terms.shape[-1]))  # a new fall begins at 0


@pytest.mark.parametrize("shaping", [0.0, 5.0])
def test_the_terms_advantages_sum_to_the_advantage_of_the_whole_reward(biped, shaping):
    """GAE is linear: with heads that sum to one critic's value, the summed per-term advantage is that
    critic's advantage of the summed reward, across a truncation and a reset — with the orientation
    shaping too (train.ppo.orientation_potential), which the orientation head takes."""
    env, batch = _rollout(biped)
    potential = OrientationPotential(biped, shaping) if shaping else None
    if potential is not None:
        potential.shape(batch, 0.99)
    k, obs_dim = len(env.rewards.names), batch["critic"].shape[-1]
    actor = make_actor(batch["policy"].shape[-1], batch["action"].shape[-1], [16], 0.3)
    heads, whole = make_critic(obs_dim, [16], heads=k), make_critic(obs_dim, [16])
    torch.manual_seed(0)
    for p in value_net(heads).parameters():  # away from the near-zero init, so the values matter
        p.data.normal_(0.0, 0.5)
    whole.load_state_dict(heads.state_dict() | {
        "module.value.2.weight": value_net(heads).value[-1].weight.sum(0, keepdim=True),
        "module.value.2.bias": value_net(heads).value[-1].bias.sum(0, keepdim=True),
    })  # fmt: skip
    by_term = batch.clone()
    one_lam = PPOConfig(term_lam=None)  # linear only with one λ for every head (the default's differs for orientation)
    PPO(actor, heads, one_lam, potential=potential, rewards=env.rewards)._gae_per_term(by_term)
    with torch.no_grad():
        PPO(actor, whole, PPOConfig(value_per_term=False), potential=potential).gae(batch)
    assert by_term["value_target"].shape == (3, 30, k)
    torch.testing.assert_close(by_term["advantage"], batch["advantage"], atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(by_term["value_target"].sum(-1, keepdim=True), batch["value_target"], atol=1e-4, rtol=1e-4)
    assert batch["advantage"].std() > 0.1


@pytest.mark.parametrize("per_component", [False, True])
def test_value_heads_per_term_or_per_component(biped, per_component):
    """value_per_term: the impact columns add up into one impact head (and GAE sees the term's reward);
    value_per_component: a head per column."""
    from fallkit.rl.value_heads import value_heads

    env, batch = _rollout(biped)
    names, column_head = value_heads(env.rewards, PPOConfig(value_per_component=per_component))
    assert names == (env.rewards.columns if per_component else env.rewards.names)
    obs_dim = batch["critic"].shape[-1]
    actor = make_actor(batch["policy"].shape[-1], batch["action"].shape[-1], [16], 0.3)
    ppo = PPO(actor, make_critic(obs_dim, [16], heads=len(names)), PPOConfig(value_per_component=per_component),
              rewards=env.rewards)  # fmt: skip
    advantages = ppo._gae_per_term(batch)
    assert advantages.shape[-1] == len(names) == batch["value_target"].shape[-1]
    if not per_component:
        assert column_head.tolist() == [0] * len(biped.component_names) + list(range(1, len(names)))


def test_a_value_per_component_needs_a_value_per_term():
    with pytest.raises(ValueError, match="value_per_component=true needs train.ppo.value_per_term=true"):
        PPOConfig(value_per_term=False, value_per_component=True)


@pytest.mark.parametrize("per_component", [False, True])
@pytest.mark.parametrize("option, default, own", [("lam", 0.95, (0.99, 0.8)), ("gamma", 0.99, (0.995, 0.9))])
def test_a_terms_own_lambda_or_gamma_changes_its_heads_advantage_alone(biped, per_component, option, default, own):
    """train.ppo.term_lam / term_gamma: the orientation head's advantage and value target are GAE with its
    λ or γ, every other head's with the run's — exactly what running each head alone with its setting gives
    (per component: the impact's heads all take the impact term's)."""
    from fallkit.rl.value_heads import value_heads

    env, batch = _rollout(biped)
    actor = make_actor(batch["policy"].shape[-1], batch["action"].shape[-1], [16], 0.3)
    own_setting = {"orientation": own[0], "impact": own[1]}
    names = value_heads(env.rewards, PPOConfig(value_per_component=per_component))[0]
    critic = make_critic(batch["critic"].shape[-1], [16], heads=len(names))
    torch.manual_seed(0)
    for p in value_net(critic).parameters():  # away from the near-zero init, so the values matter
        p.data.normal_(0.0, 0.5)

    def gae(data, **ppo):
        cfg = PPOConfig(value_per_component=per_component, **{"term_lam": None, **ppo})  # only the asked setting
        return PPO(actor, critic, cfg, rewards=env.rewards)._gae_per_term(data)

    mixed = batch.clone()
    advantages = gae(mixed, **{f"term_{option}": own_setting})
    alone = {}
    for value in (default, *own):
        alone[value] = batch.clone()
        alone[value]["terms_advantage"] = gae(alone[value], **{option: value})
    for k, head in enumerate(names):
        want = alone[own_setting.get(head.split("/")[0], default)]
        torch.testing.assert_close(advantages[..., k], want["terms_advantage"][..., k], atol=1e-4, rtol=1e-4)
        torch.testing.assert_close(mixed["value_target"][..., k], want["value_target"][..., k], atol=1e-4, rtol=1e-4)
    orientation = names.index("orientation")
    assert not torch.allclose(advantages[..., orientation], alone[default]["terms_advantage"][..., orientation])
    torch.testing.assert_close(mixed["advantage"], advantages.sum(-1, keepdim=True))


def test_a_terms_own_lambda_and_gamma_are_checked():
    from fallkit.errors import ConfigError
    from fallkit.rl.value_heads import per_head

    with pytest.raises(ValueError, match=r"term_lam.orientation=1.5: a GAE λ lies in \[0, 1\]"):
        PPOConfig(term_lam={"orientation": 1.5})
    with pytest.raises(ValueError, match=r"term_gamma.orientation=1.0: a term's discount lies in \(0, 1\)"):
        PPOConfig(term_gamma={"orientation": 1.0})
    with pytest.raises(ValueError, match="term_lam needs train.ppo.value_per_term=true"):
        PPOConfig(value_per_term=False, term_lam={"orientation": 0.99})
    with pytest.raises(ValueError, match="term_gamma needs train.ppo.value_per_term=true"):
        PPOConfig(value_per_term=False, term_gamma={"orientation": 0.995})
    with pytest.raises(ConfigError, match="orientaton is not a reward term of this run; the terms: impact, orient"):
        per_head(["impact", "orientation"], PPOConfig(term_lam={"orientaton": 0.99}), "term_lam")
    with pytest.raises(ConfigError, match="term_gamma: orientaton is not a reward term"):
        per_head(["impact", "orientation"], PPOConfig(term_gamma={"orientaton": 0.995}), "term_gamma")
    assert per_head(["impact", "orientation"], PPOConfig(term_lam=None), "term_lam") is None
    # the default's λ for the orientation term, and nothing when a run has no orientation term
    assert per_head(["impact", "orientation"], PPOConfig(), "term_lam").tolist() == pytest.approx([0.95, 0.4])
    assert per_head(["impact", "joints"], PPOConfig(), "term_lam") is None
    with pytest.raises(ConfigError, match="orientation is not a reward term"):  # set by the user, it must exist
        per_head(["impact", "joints"], PPOConfig(term_lam={"orientation": 0.9}), "term_lam")
    assert PPOConfig(value_per_term=False).term_lam == {}  # one value, one λ: the default dropped


def test_a_terms_own_lambda_and_gamma_from_the_command_line(tmp_path):
    from helpers import TINY, composed_config

    from fallkit.rl.trainer import Trainer

    overrides = ("train.iterations=1", "train.ppo.term_lam.orientation=0.99")  # the default's key: no `+`
    overrides += ("+train.ppo.term_gamma.orientation=0.995",)
    trainer = Trainer(composed_config(*TINY, *overrides), tmp_path)
    names = trainer.ppo.term_names
    assert trainer.ppo.head_lam.tolist() == pytest.approx([0.99 if n == "orientation" else 0.95 for n in names])
    assert trainer.ppo.head_gamma.tolist() == pytest.approx([0.995 if n == "orientation" else 0.99 for n in names])
    assert trainer.run().exists()  # a run with both trains


def test_training_with_a_value_per_term_logs_each_terms_advantage_and_loads(tmp_path):
    from helpers import TINY, composed_config

    from fallkit.eval.choice import critic_values
    from fallkit.rl.policy import load_policy
    from fallkit.rl.trainer import Trainer

    trainer = Trainer(composed_config(*TINY, "train.iterations=2"), tmp_path)  # value_per_term: the default
    names = trainer.env.rewards.names
    last = trainer.run()
    header = (tmp_path / "metrics.csv").read_text().splitlines()[0].split(",")
    assert {f"advantage_std/{name}" for name in names} <= set(header)
    critic = load_policy(last).critic
    obs = torch.randn(2, critic.norm.mean.shape[0])
    assert critic(obs).shape == (2, len(names))
    goal = torch.tensor([[1.0, 0.0, 0.0, 0.0]]), torch.zeros(1, trainer.env.goal_joint_pos.shape[1])
    columns = {"goal_root_quat": slice(0, 4), "goal_joint_pos": slice(4, 4 + goal[1].shape[1])}
    values = critic_values(critic, obs, *goal, columns)  # eval.poses=auto scores V(s, g) = Σ heads
    expected = obs.clone()
    expected[:, :4], expected[:, columns["goal_joint_pos"]] = goal[0], goal[1]
    torch.testing.assert_close(values[:, 0], critic(expected).sum(-1))


def test_each_value_head_normalises_its_own_targets(tmp_path):
    """train.ppo.normalize_value with a value per term: every head has its own target statistics, the
    offset's returns are positive and every penalty's negative, and each is logged under its term."""
    from helpers import TINY, composed_config

    from fallkit.rl.trainer import Trainer

    trainer = Trainer(composed_config(*TINY, "train.iterations=2", "train.ppo.normalize_value=true"), tmp_path)
    names = trainer.env.rewards.names
    trainer.run()
    target = value_net(trainer.critic).target
    assert target.mean.shape == (len(names),) and target.count > 0
    assert target.mean[names.index("offset")] > 0 and target.mean[names.index("impact")] < 0
    header = (tmp_path / "metrics.csv").read_text().splitlines()[0].split(",")
    assert {f"value_target_std/{name}" for name in names} <= set(header)


def test_a_conditioned_critic_scales_each_components_impact_head_by_its_weight_squared(tmp_path):
    """train.ppo.value_per_component with sensitivity inputs: head "impact/<c>" is the MLP's output times
    w_c², w_c read from the critic's own observation (ln w_c); other heads are the MLP's; a loaded
    checkpoint scales alike."""
    from helpers import TINY, composed_config

    from fallkit.rl.models import ValueNet
    from fallkit.rl.policy import load_policy
    from fallkit.rl.value_heads import value_heads
    from fallkit.rl.trainer import Trainer

    on = ["env.sensitivity_inputs.enabled=true", "train.ppo.value_per_component=true", "train.iterations=1",
          "train.early_reward_factor=null"]  # Table I's weights: the loaded critic then predicts what it trained to
    trainer = Trainer(composed_config(*TINY, *on), tmp_path)
    names = value_heads(trainer.env.rewards, trainer.config.train.ppo)[0]
    net = value_net(trainer.critic)
    obs = trainer.env.reset()["critic"]
    for i, c in enumerate(trainer.spec.component_names):  # each impact head reads its own component's ln w
        torch.testing.assert_close(obs[:, net.weight_columns[names.index(f"impact/{c}")]], trainer.env.sensitivity[:, i].log())
    assert (net.weight_columns[len(trainer.spec.component_names) :] == -1).all()
    plain = ValueNet(obs.shape[-1], [16, 16], precision=net.precision, heads=len(names))
    plain.load_state_dict({k: v for k, v in net.state_dict().items() if k != "weight_columns"})
    with torch.no_grad():
        scaled, unscaled = net(obs), plain(obs)
    squared = trainer.env.sensitivity.square()
    torch.testing.assert_close(scaled[:, : squared.shape[1]], unscaled[:, : squared.shape[1]] * squared)
    torch.testing.assert_close(scaled[:, squared.shape[1] :], unscaled[:, squared.shape[1] :])
    loaded = load_policy(trainer.run()).critic
    assert torch.equal(loaded.weight_columns, net.weight_columns)
    net.precision = "float32"  # as loaded policies compute
    with torch.no_grad():
        torch.testing.assert_close(loaded(obs), net(obs))


def test_weighted_impact_heads_refuse_value_target_normalisation():
    from helpers import composed_config

    from fallkit.config import ConfigError

    on = ["env.sensitivity_inputs.enabled=true", "train.ppo.value_per_component=true", "train.ppo.normalize_value=true"]
    with pytest.raises(ConfigError, match="set normalize_value=false"):
        composed_config(*on)
