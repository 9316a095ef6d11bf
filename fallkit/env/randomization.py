"""Per-episode domain randomisation (`env.randomization`): what a sim-to-real user expects.

Each is drawn per world when its episode starts, from the env's generator, and only when
enabled (so a run without randomisation draws exactly the numbers it drew before):

  friction      sliding friction of every geom, uniform in [low, high]; the critic observes
                it (paper Sec. V-A: "privileged observations … friction parameters")
  gain_scale    the PD gains kp, kd × a factor: actuator strength
  action_delay  with this chance, an episode applies each action one policy step late
                (the setpoint of a_{t−1}), a controller a step behind its estimator

Evaluation switches every one off (fallkit.eval.evaluate.eval_run_config), as it does noise
and disturbances. Not randomised yet: link masses, joint damping and armature.
"""

from __future__ import annotations

import torch

from fallkit.config.env import RandomizationConfig, RandomRange
from fallkit.sim.base import BatchSim


class EpisodeRandomization:
    """The randomised quantities of every world, drawn at reset and applied to the simulator."""

    def __init__(self, config: RandomizationConfig, sim: BatchSim, base_friction: float, device: torch.device):
        n = sim.num_worlds
        self.config, self.sim = config, sim
        self.friction = torch.full((n, 1), float(base_friction), dtype=torch.float32, device=device)
        self.gain_scale = torch.ones(n, dtype=torch.float32, device=device)
        self.delayed = torch.zeros(n, dtype=torch.bool, device=device)

    @property
    def active(self) -> bool:
        c = self.config
        return c.friction.enabled or c.gain_scale.enabled or c.action_delay > 0

    def reset(self, ids: torch.Tensor, generator: torch.Generator) -> None:
        """Draw the quantities of worlds `ids` and hand them to the simulator."""
        c, k = self.config, len(ids)
        if c.friction.enabled:
            self.friction[ids, 0] = _uniform(c.friction, k, generator, self.friction.device)
            self.sim.set_friction(self.friction[:, 0])
        if c.gain_scale.enabled:
            self.gain_scale[ids] = _uniform(c.gain_scale, k, generator, self.gain_scale.device)
            self.sim.set_gain_scale(self.gain_scale)
        if c.action_delay > 0:
            draw = torch.rand(k, generator=generator, device=self.delayed.device)
            self.delayed[ids] = draw < c.action_delay

    def applied(self, action: torch.Tensor, last_action: torch.Tensor) -> torch.Tensor:
        """The action the simulator receives: the previous one in delayed worlds."""
        if self.config.action_delay <= 0:
            return action
        return torch.where(self.delayed.view(-1, 1), last_action, action)

    def state(self) -> dict[str, torch.Tensor]:
        return {"friction": self.friction.clone(), "gain_scale": self.gain_scale.clone(), "delayed": self.delayed.clone()}

    def load(self, state: dict[str, torch.Tensor]) -> None:
        """Restore state() and hand it to the simulator again."""
        self.friction.copy_(state["friction"])
        self.gain_scale.copy_(state["gain_scale"])
        self.delayed.copy_(state["delayed"])
        if self.config.friction.enabled:
            self.sim.set_friction(self.friction[:, 0])
        if self.config.gain_scale.enabled:
            self.sim.set_gain_scale(self.gain_scale)


def _uniform(r: RandomRange, k: int, generator: torch.Generator, device: torch.device) -> torch.Tensor:
    return r.low + (r.high - r.low) * torch.rand(k, generator=generator, device=device)
