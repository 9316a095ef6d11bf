"""train.early_reward_factor: some reward terms weigh more for a run's first env steps, Table I's weights after.

Why: with Table I's weights a 15-minute biped20 policy (train=quick, 2 CPU cores) learns to soften the fall
but hardly to steer toward the end pose's tilt; the orientation term ×5 throughout makes it steer (MROE
0.95 → 0.63 of the best strategy's) and land harder (max impact 0.86 → 0.96), and ×5 first, Table I's
weight after, keeps most of the steering for less of the impact (docs/training.md, the lever table).

Whenever the weights change, the critic's heads of the reweighted terms (train.ppo.value_per_term) are
rescaled by new/old factor: a head predicts its own term's return, which is linear in the term's weight, so
its predictions stay true. That matters: a head left 5× too large keeps the ×5 credit in the advantage until
it re-fits (what a restart with Table I's weights did), and a switch at once with the head kept true undoes the
steering — hence a fade (docs/learning_log.md). One value for the whole return cannot be split that way; it
re-fits over the next updates. Checkpoints store each head's factor (`head_factors`), so a loaded critic is
brought to Table I's weights (fallkit.rl.policy, fallkit.rl.init_from).

The schedule's clock is the env steps trained, and, with train.early_within_budget, the share of the run's
budget spent (iterations or minutes, whichever ends it): its position is the larger of the env steps and that
share of the schedule's length, and it never runs back. Why: train=quick's 5.5 M env steps are the 15 minutes of
one CPU; a CPU 1.6x slower reaches 3.4 M, and by env steps alone its run ends at the ×5 weights. Off by default:
on that CPU, paired seeds 0-1, ending at Table I's weights gave max impact -0.06 for MROE +0.08 … +0.10, which
misses the MROE target the ×5 ending meets (docs/training.md). Checkpoints store the position, so a resumed run
continues from it.
"""

from __future__ import annotations

import logging

import torch

from fallkit.config import TrainConfig
from fallkit.env.rewards.context import RewardSum
from fallkit.errors import ConfigError
from fallkit.rl.models import ValueNet

log = logging.getLogger(__name__)


def in_table_one_units(critic: ValueNet, ckpt: dict) -> None:
    """A checkpoint's critic, loaded into `critic`, rescaled to Table I's weights: its heads learned the returns of
    the weights times the checkpoint's `head_factors` (none recorded: nothing to undo)."""
    if ckpt.get("head_factors"):
        critic.scale_heads(1.0 / torch.tensor(ckpt["head_factors"]))


class RewardSchedule:
    """Sets the env's reward weights for the env steps trained so far, and rescales the critic's heads when
    they change. `heads` are the critic's value heads' names (a term, a term/component, or "value")."""

    def __init__(self, config: TrainConfig, rewards: RewardSum, critic: ValueNet, heads: list[str]):
        self.early = dict(config.early_reward_factor)
        self.until, self.fade = config.early_until_env_steps, config.early_fade_env_steps
        self.rewards, self.critic = rewards, critic
        # each head's reward term (a head per component is named "<term>/<component>", as RewardSum.columns);
        # None: one value for the whole return, which has no head to rescale
        self.head_terms = None if heads == ["value"] else [head.split("/")[0] for head in heads]
        unknown = sorted(set(self.early) - set(rewards.names))
        if unknown:
            raise ConfigError(
                f"train.early_reward_factor: {', '.join(unknown)} is not a reward term of this run (terms: "
                f"{', '.join(rewards.names)}): name one of them, or drop the key with train.early_reward_factor=null"
            )
        self.factors: dict[str, float] = {}  # what the env's weights carry now ({}: the config's)
        self.within_budget = config.early_within_budget and bool(self.early)  # does it read the budget's share
        self.position = 0.0  # where on the schedule the weights are, in env steps; never runs back

    def factors_at(self, position: float) -> dict[str, float]:
        """The factors at `position` env steps into the schedule."""
        if position < self.until:
            return self.early
        left = 1.0 - (position - self.until) / self.fade if self.fade else 0.0  # the share of the early factor left
        return {name: 1.0 + (f - 1.0) * left for name, f in self.early.items()} if left > 0 else {}

    def advance(self, env_steps: int, budget_spent: float = 0.0) -> float:
        """The schedule's position after `env_steps` env steps with `budget_spent` (0-1) of the run's budget gone."""
        compressed = budget_spent * (self.until + self.fade) if self.within_budget else 0.0
        self.position = max(self.position, float(env_steps), compressed)
        return self.position

    def head_factors(self, factors: dict[str, float] | None = None) -> list[float]:
        """Each value head's factor [heads] under `factors` (default: the weights' now)."""
        factors = self.factors if factors is None else factors
        return [factors.get(term, 1.0) for term in self.head_terms or ["value"]]

    def start(
        self, env_steps: int, per_iteration: int, critic_in_table_units: bool = False, position: float | None = None
    ) -> None:
        """The weights of a run that starts (or resumes) after `env_steps`: those its last iteration collected
        with, which a resumed critic fits (a switch due at the next iteration then rescales it as usual); a
        resumed checkpoint's `position` says where they were (older checkpoints: by env steps). A critic loaded
        in Table I's units (train.init_from) is scaled to them."""
        self.position = float(max(env_steps - per_iteration, 0)) if position is None else position
        self.factors = self.factors_at(self.position)
        self.rewards.reweight(self.factors)
        if critic_in_table_units and self.head_terms:
            self.critic.scale_heads(torch.tensor(self.head_factors()))

    def step(self, env_steps: int, budget_spent: float = 0.0) -> dict[str, float]:
        """Before an iteration's collection: switch the weights if the schedule says so; each term's factor, for the log."""
        factors = self.factors_at(self.advance(env_steps, budget_spent))
        if factors != self.factors:
            if self.head_terms:
                self.critic.scale_heads(torch.tensor(self.head_factors(factors)) / torch.tensor(self.head_factors()))
            if self.factors == self.early or not factors:  # the fade's start and end, not its every step
                log.info("reward weights after %d env steps (the schedule at %d): factors %s (train.early_reward_factor)",
                         env_steps, self.position, factors or "none")
            self.factors = factors
            self.rewards.reweight(factors)
        return {f"reward_factor/{name}": self.factors.get(name, 1.0) for name in self.early}
