"""The critic's value heads: which heads a run's critic has (one for the whole return, one per reward term,
or one per reward column), each head's GAE λ and γ, and the critic built with them — read off the config in
one place for the trainer, the PPO update and the benchmarks (fallkit.rl.ppo, point 7, says how they learn)."""

from __future__ import annotations

import torch

from fallkit.config import FallkitConfig, PPOConfig
from fallkit.env.rewards.context import RewardSum
from fallkit.errors import ConfigError
from fallkit.rl.models import impact_weight_columns, make_critic
from fallkit.robots.spec import RobotSpec


def value_heads(rewards: RewardSum, cfg: PPOConfig) -> tuple[list[str], torch.Tensor | None]:
    """The value heads of a decomposed critic: one per reward term (the impact per component's columns
    summed into the impact head: `column_head`), or one per reward column with `value_per_component`."""
    if cfg.value_per_component:
        return list(rewards.columns), None
    return list(rewards.names), rewards.column_term


def per_head(head_terms: list[str], cfg: PPOConfig, option: str) -> torch.Tensor | None:
    """A GAE setting of every value head [K] (`option`: "term_lam" or "term_gamma"), given the reward term
    of each head; None when every head uses the run's own (`lam` or `gamma`)."""
    own = cfg.per_term(option, head_terms)
    if not own:
        return None
    default = getattr(cfg, option.removeprefix("term_"))
    unknown = sorted(set(own) - set(head_terms))
    if unknown:
        raise ConfigError(
            f"train.ppo.{option}: {', '.join(unknown)} is not a reward term of this run; "
            f"the terms: {', '.join(sorted(set(head_terms)))}"
        )
    return torch.tensor([own.get(term, default) for term in head_terms])


def critic_heads(config: FallkitConfig, spec: RobotSpec, rewards: RewardSum) -> tuple[list[str], list[int] | None]:
    """The critic's value heads as training builds them: their names (one per reward term or column with
    value_per_term, else one) and, for a critic that observes the sensitivity weights, each head's ln w_c
    column (ValueNet.weight_columns; None when no head is scaled)."""
    ppo = config.train.ppo
    heads = value_heads(rewards, ppo)[0] if ppo.value_per_term else ["value"]
    if not (ppo.value_per_component and config.env.sensitivity_inputs.enabled):
        return heads, None
    return heads, impact_weight_columns(spec, heads, config.env.observe_gravity)


def critic_for(config: FallkitConfig, spec: RobotSpec, rewards, obs_dim: int, precision: str) -> tuple[torch.nn.Module, list[str]]:
    """The critic a run builds from its config, and its heads' names: its layout read off the config in one place."""
    tc, (heads, weight_columns) = config.train, critic_heads(config, spec, rewards)
    args = (tc.critic_hidden, tc.ppo.normalize_value, precision, len(heads), weight_columns, tc.critic_layer_norm)
    return make_critic(obs_dim, *args), heads
