"""Exploration noise correlated in time (train.noise_correlation_time).

With white noise, each policy step's action is drawn afresh: at 50 Hz the PD loop and the body
filter most of it out, so a fall explores little beyond its mean — yet steering a fall to another
side takes a push held for a few tenths of a second. Correlated noise keeps the same per-step
distribution, a ~ N(loc, scale), but draws the unit noise from a stationary AR(1) process per
world, ε_t = ρ·ε_{t−1} + √(1 − ρ²)·ξ_t with ρ = exp(−dt / τ), restarted (ε = ξ) when an episode
starts. Each ε_t is N(0, 1), so the collected action's log-probability is its Gaussian's, as PPO's
ratio reads it (colored-noise PPO, Hollenstein et al. 2024, does the same with power-law noise; an
AR(1) needs one [N, A] state and no FFT, on any device, with no host reads).
"""

from __future__ import annotations

import math

import torch
from tensordict import TensorDict
from torchrl.modules import IndependentNormal


class CorrelatedNoise:
    """The unit noise ε [N, A] of the next policy step, one AR(1) process per world."""

    def __init__(self, num_envs: int, act_dim: int, correlation_time: float, dt: float, device: torch.device | str):
        if correlation_time <= 0:
            raise ValueError("CorrelatedNoise: correlation_time must be > 0 s (0 is white noise: use none)")
        self.rho = math.exp(-dt / correlation_time)
        self.innovation = math.sqrt(1.0 - self.rho**2)
        self.eps = torch.randn(num_envs, act_dim, device=device)  # stationary from the start

    def step(self, fresh: torch.Tensor) -> torch.Tensor:
        """Advance every world's process one step; worlds whose episode starts now (`fresh` [N]) restart."""
        xi = torch.randn_like(self.eps)
        self.eps = torch.where(fresh.unsqueeze(-1), xi, self.eps.mul(self.rho).add_(xi, alpha=self.innovation))
        return self.eps

    def act(self, td: TensorDict, fresh: torch.Tensor) -> TensorDict:
        """The action loc + scale·ε and its log-probability, from the actor's "loc" and "scale" in `td`."""
        loc, scale = td["loc"], td["scale"]
        action = torch.addcmul(loc, scale, self.step(fresh))
        td.set("action", action)
        td.set("action_log_prob", IndependentNormal(loc, scale).log_prob(action))
        return td

    def state_dict(self) -> dict[str, torch.Tensor]:
        return {"eps": self.eps.clone()}

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        if state["eps"].shape != self.eps.shape:
            raise ValueError(f"exploration noise of shape {list(state['eps'].shape)}; this run's is {list(self.eps.shape)}")
        self.eps = state["eps"].to(self.eps.device)
