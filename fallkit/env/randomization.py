"""Per-episode domain randomisation (`env.randomization`): what a sim-to-real user expects.

Each is drawn per world when its episode starts, from the env's generator, and only when
enabled (so a run without randomisation draws exactly the numbers it drew before):

  friction      sliding friction of every geom, uniform in [low, high]; the critic observes
                it (paper Sec. V-A: "privileged observations … friction parameters")
  gain_scale    the PD gains kp, kd × a factor: actuator strength
  action_delay  with this chance, an episode applies each action one policy step late
                (the setpoint of a_{t−1}), a controller a step behind its estimator
  mass          every link's mass and rotational inertia × its own factor (MuJoCo's derived
                constants recomputed per world: mj_setConst)
  joint_damping every joint's viscous damping × a factor
  armature      every joint's armature × a factor

and, with env.sensitivity_inputs, the components' sensitivity weights (`SensitivityDraw`).

Evaluation switches every one off (fallkit.eval.evaluate.eval_run_config), as it does noise
and disturbances. Masses, damping and armature are per world on the MuJoCo C backend only
(the warp backend refuses them, see fallkit.sim.warp_sim).
"""

from __future__ import annotations

import math

import torch

from fallkit.config.env import RandomizationConfig, RandomRange, SensitivityInputs
from fallkit.errors import ConfigError
from fallkit.robots.spec import RobotSpec
from fallkit.sim.base import BatchSim


class EpisodeRandomization:
    """The randomised quantities of every world, drawn at reset and applied to the simulator."""

    def __init__(self, config: RandomizationConfig, sim: BatchSim, base_friction: float, device: torch.device):
        n = sim.num_worlds
        self.config, self.sim = config, sim
        self.friction = torch.full((n, 1), float(base_friction), dtype=torch.float32, device=device)
        self.gain_scale = torch.ones(n, dtype=torch.float32, device=device)
        self.delayed = torch.zeros(n, dtype=torch.bool, device=device)
        self.mass_scale = torch.ones(n, sim.model.nbody, dtype=torch.float32, device=device)
        self.damping_scale = torch.ones(n, dtype=torch.float32, device=device)
        self.armature_scale = torch.ones(n, dtype=torch.float32, device=device)

    @property
    def active(self) -> bool:
        c = self.config
        return c.friction.enabled or c.gain_scale.enabled or c.action_delay > 0 or self._dynamics

    @property
    def _dynamics(self) -> bool:
        c = self.config
        return c.mass.enabled or c.joint_damping.enabled or c.armature.enabled

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
        if c.mass.enabled:
            b = self.mass_scale.shape[1]
            self.mass_scale[ids] = _uniform(c.mass, k * b, generator, self.mass_scale.device).view(k, b)
            self.sim.set_mass_scale(ids, self.mass_scale[ids])
        if c.joint_damping.enabled:
            self.damping_scale[ids] = _uniform(c.joint_damping, k, generator, self.damping_scale.device)
        if c.armature.enabled:
            self.armature_scale[ids] = _uniform(c.armature, k, generator, self.armature_scale.device)
        if c.joint_damping.enabled or c.armature.enabled:
            self.sim.set_joint_scale(ids, self.damping_scale[ids], self.armature_scale[ids])

    def applied(self, action: torch.Tensor, last_action: torch.Tensor) -> torch.Tensor:
        """The action the simulator receives: the previous one in delayed worlds."""
        if self.config.action_delay <= 0:
            return action
        return torch.where(self.delayed.view(-1, 1), last_action, action)

    def state(self) -> dict[str, torch.Tensor]:
        names = ("friction", "gain_scale", "delayed", "mass_scale", "damping_scale", "armature_scale")
        return {name: getattr(self, name).clone() for name in names}

    def load(self, state: dict[str, torch.Tensor]) -> None:
        """Restore state() and hand it to the simulator again."""
        self.friction.copy_(state["friction"])
        self.gain_scale.copy_(state["gain_scale"])
        self.delayed.copy_(state["delayed"])
        for name in ("mass_scale", "damping_scale", "armature_scale"):
            if name in state:  # checkpoints written before these were randomised hold none
                getattr(self, name).copy_(state[name])
        c, every = self.config, torch.arange(self.sim.num_worlds, device=self.friction.device)
        if c.friction.enabled:
            self.sim.set_friction(self.friction[:, 0])
        if c.gain_scale.enabled:
            self.sim.set_gain_scale(self.gain_scale)
        if c.mass.enabled:
            self.sim.set_mass_scale(every, self.mass_scale)
        if c.joint_damping.enabled or c.armature.enabled:
            self.sim.set_joint_scale(every, self.damping_scale, self.armature_scale)


def _uniform(r: RandomRange, k: int, generator: torch.Generator, device: torch.device) -> torch.Tensor:
    return r.low + (r.high - r.low) * torch.rand(k, generator=generator, device=device)


class SensitivityDraw:
    """The sensitivity weights [k, C] of k new episodes (env.sensitivity_inputs), on `device`: the robot's
    weights × factors log-uniform in [low, high] for the components drawn (`components`; null: all of them),
    the others at the robot's weights; draw="one": one of the drawn components per episode. Calling it gives
    None where nothing is drawn (low = high = 1 in evaluation, or the inputs off), so the worlds keep the
    weights they have."""

    def __init__(self, config: SensitivityInputs, spec: RobotSpec, device: torch.device | str = "cpu"):
        names = spec.component_names
        unknown = [c for c in config.components or () if c not in names]
        if unknown:
            raise ConfigError(f"env.sensitivity_inputs.components: {unknown} are not components of this robot; "
                              f"its components are {list(names)}")  # fmt: skip
        self.config, self.weights = config, torch.as_tensor(spec.sensitivity, dtype=torch.float32, device=device)
        drawn = [config.components is None or name in config.components for name in names]
        self.drawn = torch.tensor(drawn, device=device)  # [C]
        self.drawn_ids = torch.tensor([i for i, d in enumerate(drawn) if d], device=device)
        self.active = config.enabled and not config.low == config.high == 1.0

    def __call__(self, k: int, generator: torch.Generator | None) -> torch.Tensor | None:
        if not self.active:
            return None
        lo, hi = math.log(self.config.low), math.log(self.config.high)
        u = torch.rand(k, self.weights.shape[0], generator=generator, device=self.weights.device)
        log_factor = lo + (hi - lo) * u
        if self.config.draw == "one":  # one drawn component per episode, the others at the robot's weights
            pick = torch.randint(len(self.drawn_ids), (k, 1), generator=generator, device=self.weights.device)
            one = torch.zeros_like(log_factor, dtype=torch.bool).scatter_(1, self.drawn_ids[pick], True)
            log_factor = torch.where(one, log_factor, 0.0)
        elif self.config.components is not None:
            log_factor = torch.where(self.drawn, log_factor, 0.0)
        return self.weights * torch.exp(log_factor)
