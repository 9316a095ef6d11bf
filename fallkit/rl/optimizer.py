"""Adam with rsl_rl's KL-adaptive learning rate, decided on the device (paper Table III: adaptive lr).

Before each minibatch's step the KL between the collecting policy and the current one sets the
actor's rate: KL > 2·target → lr / 1.5, KL < target / 2 → lr · 1.5, within [lr_min, lr_max]. The
critic's rate follows it too unless it has its own (`critic_learning_rate`): a KL-bound step is about
the policy, and ties the critic to it.

Why tensors: deciding on the host would read the KL back at every minibatch, and on a GPU each read
waits for the launch queue to drain. So the rule's state is a float64 tensor on the device (the same
arithmetic as Python floats), each group's rate the float32 tensor Adam reads, and Adam runs fused
(one kernel per group, its step counters on the device; a tensor rate needs `fused` or `capturable`
on a GPU, and on the CPU fused is the fast path too).
"""

from __future__ import annotations

import torch

from fallkit.config import PPOConfig


def adapt_learning_rate(lr: torch.Tensor, kl: torch.Tensor, cfg: PPOConfig) -> torch.Tensor:
    """rsl_rl's rule: shrink the step when the policy moved too far, grow it when too little.

    On the device, with no host read: `lr` is a float64 scalar tensor (the same arithmetic as
    Python floats), `kl` the minibatch's KL; a NaN KL leaves the rate as it is.
    """
    if cfg.desired_kl is None:
        return lr
    kl = kl.to(lr.dtype)
    smaller, larger = (lr / 1.5).clamp(min=cfg.lr_min), (lr * 1.5).clamp(max=cfg.lr_max)
    grow = (kl > 0.0) & (kl < cfg.desired_kl / 2.0)
    return torch.where(kl > 2.0 * cfg.desired_kl, smaller, torch.where(grow, larger, lr))


class AdaptiveAdam:
    """Adam over two groups, the actor's parameters and the critic's, with the KL rule on the device."""

    def __init__(self, actor_params: list[torch.Tensor], critic_params: list[torch.Tensor], cfg: PPOConfig):
        self.cfg = cfg
        device = actor_params[0].device
        self.learning_rate = torch.tensor(cfg.learning_rate, dtype=torch.float64, device=device)
        self.group_rates = [torch.tensor(cfg.learning_rate, device=device) for _ in range(2)]
        if cfg.critic_learning_rate is not None:
            self.group_rates[1].fill_(cfg.critic_learning_rate)
        self.fused = device.type in ("cpu", "cuda")
        groups = [{"params": params, "lr": rate} for params, rate in zip((actor_params, critic_params), self.group_rates)]
        self.optimizer = torch.optim.Adam(groups, fused=self.fused or None)

    @property
    def param_groups(self) -> list[dict]:
        return self.optimizer.param_groups

    def adapt(self, kl: torch.Tensor) -> None:
        """The rule, given this minibatch's KL, before its step."""
        self.learning_rate = adapt_learning_rate(self.learning_rate, kl, self.cfg)
        self.group_rates[0].copy_(self.learning_rate)
        if self.cfg.critic_learning_rate is None:
            self.group_rates[1].copy_(self.learning_rate)

    def start_at(self, rate: float) -> None:
        """The actor's rate (and the critic's, where it follows the actor's) before the first step."""
        self.learning_rate.fill_(rate)
        self.group_rates[0].fill_(rate)
        if self.cfg.critic_learning_rate is None:
            self.group_rates[1].fill_(rate)

    def zero_grad(self) -> None:
        self.optimizer.zero_grad(set_to_none=True)

    def step(self) -> None:
        self.optimizer.step()

    def state_dict(self) -> dict:
        return {"optimizer": self.optimizer.state_dict(), "learning_rate": float(self.learning_rate)}

    def load_state_dict(self, state: dict) -> None:
        """The optimizer and the rate of a checkpoint, this form's or one saved before the rates were
        tensors and Adam fused (a float rate, step counters on the host): those are brought to this form."""
        self.optimizer.load_state_dict(state["optimizer"])
        self.learning_rate.fill_(float(state["learning_rate"]))
        for group, rate in zip(self.optimizer.param_groups, self.group_rates):
            rate.fill_(float(group["lr"]))
            group.update(lr=rate, fused=self.fused or None, foreach=None)
            for p in group["params"]:
                step = self.optimizer.state.get(p, {}).get("step")
                if self.fused and step is not None:
                    self.optimizer.state[p]["step"] = torch.as_tensor(step, dtype=torch.float32, device=p.device)
