"""Random disturbance wrenches on named bodies (paper Sec. V-A, Table IV).

Each disturbed body alternates between "off" and "on" periods of random length.
When a period turns on, a new force and torque are drawn, uniform per axis in
[−max, max] (Table IV's magnitudes per dimension, random sign); they act at the
body's centre of mass, world frame, until the period ends. The robot spec names
which bodies play each role (`RobotSpec.disturbance_bodies`); roles the robot
does not name are skipped, roles it names but this config lacks are not disturbed.

All worlds and bodies are scheduled at once with torch ops: no Python per world.
"""

from __future__ import annotations

import torch

from fallkit.config import DisturbanceConfig
from fallkit.robots.spec import RobotSpec


class Disturbances:
    """On/off schedules and wrenches of every disturbed body in every world.

    `reset(mask)` starts the masked worlds in an "off" period of random length in
    [0, off_max] (so a disturbance can come early in short episodes);
    `step(dt)` advances all schedules by dt and returns the wrenches [N, K, 6]
    (force xyz, torque xyz) to apply to `body_ids` during the next step.
    """

    def __init__(self, spec: RobotSpec, config: DisturbanceConfig, num_worlds: int, device: torch.device | str = "cpu"):
        m = spec.mj_model()
        names, ranges = [], []
        for role, bodies in spec.disturbance_bodies.items():
            if role not in config.roles:
                continue
            for body in bodies:
                try:
                    m.body(body)
                except KeyError:
                    raise ValueError(f"robot '{spec.name}': disturbance_bodies.{role}: no body '{body}'") from None
                names.append(body)
                ranges.append(config.roles[role])
        self.body_names = names
        self.body_ids = torch.tensor([m.body(b).id for b in names], dtype=torch.long)
        self.num_worlds = num_worlds
        self.device = torch.device(device)
        k = len(names)

        def col(values: list[float]) -> torch.Tensor:
            return torch.tensor(values, dtype=torch.float32, device=self.device)

        on_lo, on_hi = col([r.on_time[0] for r in ranges]), col([r.on_time[1] for r in ranges])
        off_lo, off_hi = col([r.off_time[0] for r in ranges]), col([r.off_time[1] for r in ranges])
        self._on, self._on_span = on_lo, on_hi - on_lo
        self._off, self._off_span, self._off_hi = off_lo, off_hi - off_lo, off_hi
        # per body: force max on xyz, torque max on xyz
        self._max = torch.stack([col([r.force] * 3 + [r.torque] * 3) for r in ranges]) if k else col([]).view(0, 6)
        self.active = torch.zeros(num_worlds, k, dtype=torch.bool, device=self.device)
        self.remaining = torch.zeros(num_worlds, k, device=self.device)  # [s] left in the current period
        self.wrench = torch.zeros(num_worlds, k, 6, device=self.device)

    def __len__(self) -> int:
        return len(self.body_names)

    def reset(self, mask: torch.Tensor, generator: torch.Generator) -> None:
        """Start the worlds where `mask` [N] is True in an 'off' period."""
        m = mask.view(-1, 1)
        u = torch.rand(self.remaining.shape, generator=generator, device=self.device)
        self.remaining = torch.where(m, u * self._off_hi, self.remaining)
        self.active = self.active & ~m
        self.wrench = self.wrench * ~m.unsqueeze(-1)

    def step(self, dt: float, generator: torch.Generator) -> torch.Tensor:
        """Advance every schedule by dt; the wrenches [N, K, 6] for the coming step."""
        n, k = self.remaining.shape
        g, dev = generator, self.device
        remaining = self.remaining - dt
        flip = remaining <= 0.0
        active = self.active ^ flip
        # a fresh duration for every period that just began, from its on or off range;
        # the overshoot is carried so periods keep their drawn lengths on the dt grid
        lo = torch.where(active, self._on, self._off)
        span = torch.where(active, self._on_span, self._off_span)
        duration = torch.addcmul(lo, torch.rand(n, k, generator=g, device=dev), span)
        self.remaining = torch.where(flip, remaining + duration, remaining)
        # a new wrench for every period that just turned on, uniform per axis in [−max, max]
        fresh = torch.rand(n, k, 6, generator=g, device=dev).sub_(0.5).mul_(2.0 * self._max)
        wrench = torch.where((flip & active).unsqueeze(-1), fresh, self.wrench)
        self.wrench = wrench * active.unsqueeze(-1)
        self.active = active
        return self.wrench


def disturbances(spec: RobotSpec, num_worlds: int, device: torch.device | str = "cpu", **config) -> Disturbances:
    """Entry point `disturbances` of group fallkit.samplers: factory(spec, num_worlds, device, **config)."""
    return Disturbances(spec, DisturbanceConfig(**config), num_worlds, device)
