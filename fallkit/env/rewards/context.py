"""The batch a reward term sees, the reward config, and the weighted sum (paper Table I).

A reward term is a registered plugin (entry-point group `fallkit.rewards`): a pure
function `term(ctx: RewardContext) -> Tensor [N]` returning its UNWEIGHTED value
per world (penalties negative, the offset +1). The environment multiplies each
term by its config weight and by the policy step dt and sums them:

    r_t = policy_dt · Σ_k weight_k · term_k(ctx)

Scaling by dt (as rsl_rl / Isaac Lab reward managers do) makes Table I's weights
rate-independent: the +50 offset earns 1.0 per 50 Hz step, 50 per simulated second.
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

    Keeps the per-term mean over worlds of each step's weighted contribution
    (weight · term · dt, what enters the reward), for logging.
    """

    def __init__(self, config: RewardConfig, dt: float, device: torch.device | str = "cpu"):
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
        self.scale = torch.tensor([w * dt for w in active.values()], device=device)  # [K]
        self.last_mean = torch.zeros(len(self.names), device=device)
        self._sum = torch.zeros(len(self.names), device=device)
        self._count = 0

    def __call__(self, ctx: RewardContext) -> torch.Tensor:
        """The reward [N] of one step."""
        return self.contributions(ctx).sum(dim=1)

    def contributions(self, ctx: RewardContext) -> torch.Tensor:
        """Each term's weighted contribution (weight · term · dt) [N, K], in `names` order; the reward is their sum."""
        n = ctx.action.shape[0]
        if not self.functions:
            return torch.zeros(n, 0, device=ctx.action.device)
        values = torch.stack([_checked(name, fn(ctx), n) for name, fn in zip(self.names, self.functions)], dim=1)
        weighted = values * self.scale
        self.last_mean = weighted.mean(dim=0)
        self._sum += self.last_mean
        self._count += 1
        return weighted

    def pop_means(self) -> dict[str, float]:
        """Per-term mean contribution per step since the last call (then starts over)."""
        if self._count == 0:
            return {}
        means = (self._sum / self._count).tolist()
        self._sum.zero_()
        self._count = 0
        return dict(zip(self.names, means))


def _checked(name: str, value: Any, n: int) -> torch.Tensor:
    if not isinstance(value, torch.Tensor) or value.shape != (n,):
        got = list(value.shape) if isinstance(value, torch.Tensor) else type(value).__name__
        raise ValueError(f"reward term '{name}' must return a tensor of shape [{n}], got {got}")
    return value
