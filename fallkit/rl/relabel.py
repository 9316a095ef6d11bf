"""Hindsight sensitivity weights: every collected fall also teaches the same fall under other weights.

With env.sensitivity_inputs a policy must learn what the weights it observes ask of it, from
episodes that each show one draw of the weights, and at these budgets it barely does
(docs/sensitivity_inputs.md: the head at 4x moves its p95 max force ~5 %). Yet the weights change
nothing in the physics: they only price the contact forces, and the environment reports each
component's priced peak as a reward column of its own, weight·dt·(−(w_c ‖f_c‖∞)²). So a collected
rollout is as well a rollout under any other weights w': the same states and actions, ln w' in the
observations, each component's impact column times (w'_c / w_c)². `SensitivityRelabel` makes that
copy, w' drawn per world as the env draws an episode's weights (`draw_sensitivity`), one draw for
the world's whole rollout; PPO (`train.ppo.relabel_sensitivity`) runs GAE on it with the critic
reading w' and trains on both, so every minibatch holds the same actions priced two ways: the
contrast that says what a weight input means.

The copy's actions were drawn by the policy at w, not at w'. PPO (`PPO._reweigh_relabelled`) takes
the collecting policy's log-probability at the copy's observation as the copy's old one, so the ratio
π_θ(a | o') / π_old(a | o') starts at 1, and scales the copy's advantage by the truncated importance
weight min(1, π_old(a | o') / π_old(a | o)) of an action drawn at o (V-trace's ρ̄; hindsight policy
gradients weigh relabelled goals alike, Rauber et al. 2019). The later actions of the rollout are the
policy's at w too; that stays uncorrected, as PPO leaves the epochs' reuse of a batch uncorrected.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

from fallkit.config.env import SensitivityInputs
from fallkit.env.observations import actor_slices, sensitivity_input
from fallkit.env.randomization import draw_sensitivity
from fallkit.env.rewards.context import RewardSum
from fallkit.env.rewards.impact import impact
from fallkit.errors import ConfigError
from fallkit.robots.spec import RobotSpec


class SensitivityRelabel:
    """Copies of collected rollouts under newly drawn sensitivity weights (see the module's docstring).

    The critic observation starts with the actor's (fallkit.env.observations), so ln w sits in the
    same columns of both. Weights are read back from the observation (ln w), so a weight below
    MIN_SENSITIVITY is priced as the policy observed it.
    """

    def __init__(self, spec: RobotSpec, inputs: SensitivityInputs, rewards: RewardSum, gravity: bool = False):
        if not inputs.enabled or inputs.low == inputs.high:
            raise ConfigError(
                "train.ppo.relabel_sensitivity draws other sensitivity weights for the collected falls: it needs "
                "env.sensitivity_inputs.enabled=true with low < high"
            )
        if "impact" not in rewards.names or rewards.functions[rewards.names.index("impact")] is not impact:
            raise ConfigError(
                "train.ppo.relabel_sensitivity reprices the built-in impact term, −(w_c ‖f_c‖∞)² per component; "
                "this run's reward has no such term (reward.impact=0 or reward.terms.impact replaced): switch it off"
            )
        self.inputs = inputs
        self.robot_weights = torch.as_tensor(spec.sensitivity, dtype=torch.float32)  # [C], drawn from on the CPU
        self.columns = actor_slices(spec, sensitivity=True, gravity=gravity)["sensitivity"]
        term = rewards.names.index("impact")
        self.impact_columns = torch.nonzero(rewards.column_term.cpu() == term).squeeze(-1)  # [C], component order

    def __call__(self, batch: TensorDictBase, generator: torch.Generator | None = None) -> TensorDictBase:
        """The copy of an [N, T] batch (holding "policy", "critic", ("next", "critic") and ("next",
        "reward_terms"); every other key as it is) under weights drawn per world."""
        observed = batch["policy"][..., self.columns]  # [N, T, C]: ln w of each step's episode
        device = observed.device
        drawn = draw_sensitivity(self.inputs, self.robot_weights, batch.shape[0], generator)  # [N, C]
        new = sensitivity_input(drawn).to(device).unsqueeze(1)  # [N, 1, C]: ln w', the world's whole rollout
        price = torch.exp(2.0 * (new - observed))  # (w' / w)² per step and component
        terms = batch["next", "reward_terms"].clone()
        terms[..., self.impact_columns.to(device)] *= price
        image = batch.clone(recurse=False)
        for key in ("policy", "critic", ("next", "policy"), ("next", "critic")):
            if key in batch.keys(include_nested=True):
                image.set(key, _with_columns(batch[key], self.columns, new))
        image.set(("next", "reward_terms"), terms)
        image.set(("next", "reward"), terms.sum(dim=-1, keepdim=True))
        return image


def _with_columns(obs: torch.Tensor, columns: slice, values: torch.Tensor) -> torch.Tensor:
    out = obs.clone()
    out[..., columns] = values.expand(*obs.shape[:-1], values.shape[-1])
    return out
