"""The batch a reward term sees, the reward config, and the weighted sum (paper Table I).

A reward term is a registered plugin (entry-point group `fallkit.rewards`): a pure
function `term(ctx: RewardContext) -> Tensor [N]` returning its UNWEIGHTED value
per world (penalties negative, the offset +1). The environment multiplies each
term by its config weight and by the policy step dt and sums them:

    r_t = policy_dt · Σ_k weight_k · term_k(ctx)

Scaling by dt (as rsl_rl / Isaac Lab reward managers do) makes Table I's weights
rate-independent: the +50 offset earns 1.0 per 50 Hz step, 50 per simulated second.

A term that is a sum over the robot's components may also offer its summands as
`term.by_component(ctx) -> Tensor [N, C]` (the built-in `impact` does). Given the
component names, `RewardSum` then reports them as separate columns
("impact/head", ...): the reward is the same sum, and a critic can keep a value
per column (train.ppo.value_per_component).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import torch

from fallkit import registry
from fallkit.config import RewardConfig
from fallkit.sim.base import SimState

RewardTerm = Callable[["RewardContext"], torch.Tensor]

# Built-in terms in Table I order; each is also the entry-point name of its function.


@dataclass
class RewardContext:
    """One policy step of N worlds, everything on the environment's device.

    `state` is the simulator state after the step (SimState documents frames and
    units). Actions are the policy's outputs (setpoint = nominal + action_scale · a).
    """

    state: SimState
    action: torch.Tensor  # [N, J] a_t
    last_action: torch.Tensor  # [N, J] a_{t-1}
    last_last_action: torch.Tensor  # [N, J] a_{t-2}
    target_root_quat: torch.Tensor  # [N, 4] θ̂_t, world frame: the end pose aligned with the current heading
    target_joint_pos: torch.Tensor  # [N, J] q̂_t [rad]
    sensitivity: torch.Tensor  # [N, C] w_c of every world ([C] broadcasts), component order of the robot spec
    time: torch.Tensor  # [N] seconds since the episode began, at the end of this step
    blend: torch.Tensor  # [N] u(t) ∈ [0, 1], the tracking blend (fallkit.env.rewards.tracking.blend)
    force_unit: float  # newtons per force unit of the impact term (1000: kN)
    force_clip: float | None  # clip of each force component [force units]; None = no clipping
    dt: float  # policy step [s]




class RewardSum:
    """Loads the active terms from the registry and sums them, weighted, times dt.

    `columns` are the reward's summands as reported (`contributions`): one per term, or one per
    component for a term that offers `by_component` when `components` are given; `column_term[i]`
    is the index in `names` of column i's term. Keeps the per-term mean over worlds of each step's
    weighted contribution (weight · term · dt, what enters the reward), for logging.
    """

    def __init__(
        self,
        config: RewardConfig,
        dt: float,
        device: torch.device | str = "cpu",
        components: list[str] | None = None,
    ):
        self.config = config
        self.dt = dt
        active = {k: w for k, w in config.weights().items() if w != 0.0}
        unknown = sorted(set(config.terms) - set(config.weights()))
        if unknown:
            raise ValueError(f"reward.terms: {unknown} have no weight; give one with +reward.<name>=<weight>")
        self.names: list[str] = list(active)
        self.functions: list[RewardTerm] = [
            registry.load("fallkit.rewards", config.terms.get(name, name)) for name in self.names
        ]
        self.num_components = len(components or [])
        self.split = [components is not None and hasattr(fn, "by_component") for fn in self.functions]
        self.any_split = any(self.split)
        self.columns: list[str] = []
        column_term: list[int] = []
        for k, (name, split) in enumerate(zip(self.names, self.split)):
            parts = [f"{name}/{c}" for c in components] if split else [name]
            self.columns += parts
            column_term += [k] * len(parts)
        self.column_term = torch.tensor(column_term, dtype=torch.long, device=device)
        self.weights = torch.tensor(list(active.values()), device=device)  # [names], the config's
        self.scale = self.weights[self.column_term] * dt  # [columns]
        self.last_mean = torch.zeros(len(self.names), device=device)
        self._sum = torch.zeros(len(self.names), device=device)
        self._count = 0

    def reweight(self, factors: dict[str, float]) -> None:
        """Each named term's config weight times its factor from now on (train.early_reward_factor); the terms
        not named keep their config weight, so `reweight({})` restores them all."""
        unknown = sorted(set(factors) - set(self.names))
        if unknown:
            raise ValueError(
                f"{', '.join(unknown)} is not a reward term of this run (a weight of 0 drops a term); "
                f"the terms: {', '.join(self.names)}"
            )
        factor = torch.tensor([factors.get(name, 1.0) for name in self.names], device=self.weights.device)
        self.scale = (self.weights * factor)[self.column_term] * self.dt

    def __call__(self, ctx: RewardContext) -> torch.Tensor:
        """The reward [N] of one step."""
        return self.contributions(ctx).sum(dim=1)

    def contributions(self, ctx: RewardContext) -> torch.Tensor:
        """Each column's weighted contribution (weight · term · dt) [N, len(columns)], in `columns` order;
        the reward is their sum."""
        n = ctx.action.shape[0]
        if not self.functions:
            return torch.zeros(n, 0, device=ctx.action.device)
        parts = [
            _checked_columns(name, fn.by_component(ctx), n, self.num_components) if split else _checked(name, fn(ctx), n)
            for name, fn, split in zip(self.names, self.functions, self.split)
        ]
        weighted = torch.column_stack(parts) * self.scale  # a [N] term is one column, an [N, C] one C columns
        column_mean = weighted.mean(dim=0)
        if self.any_split:  # the split terms' columns summed back into their term
            column_mean = torch.zeros_like(self._sum).index_add_(0, self.column_term, column_mean)
        self.last_mean = column_mean
        self._sum += self.last_mean
        self._count += 1
        return weighted

    def pop_means(self) -> dict[str, float]:
        """Per-term mean contribution per step since the last call (then starts over)."""
        means = self.pop_mean_tensor()
        return dict(zip(self.names, means.tolist())) if means is not None else {}

    def pop_mean_tensor(self) -> torch.Tensor | None:
        """`pop_means` as one [len(names)] tensor on the device, nothing read back (None: no step since)."""
        if self._count == 0:
            return None
        means = self._sum / self._count
        self._sum.zero_()
        self._count = 0
        return means


def _checked(name: str, value: Any, n: int) -> torch.Tensor:
    if not isinstance(value, torch.Tensor) or value.shape != (n,):
        got = list(value.shape) if isinstance(value, torch.Tensor) else type(value).__name__
        raise ValueError(f"reward term '{name}' must return a tensor of shape [{n}], got {got}")
    return value


def _checked_columns(name: str, value: Any, n: int, c: int) -> torch.Tensor:
    if not isinstance(value, torch.Tensor) or value.shape != (n, c):
        got = list(value.shape) if isinstance(value, torch.Tensor) else type(value).__name__
        raise ValueError(f"reward term '{name}': by_component must return a tensor of shape [{n}, {c}], got {got}")
    return value
