"""Settling poses by dropping them: the at-rest test and the plain (non-refilling) drop.

A pose is dropped with the actuators frozen (gains x `gain_scale`, holding a
setpoint) until root and joint speeds stay below the thresholds of
`SettleConfig` for `rest_time`, or it is given up at `max_time`. `settle` does
this for a fixed batch of poses (artist poses, checks); the generator runs the
same test in a refilling pool (`fallkit.poses.generator`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch

from fallkit.config import SettleConfig
from fallkit.robots.spec import RobotSpec
from fallkit.sim import Layout, SimState, make_sim


@dataclass
class CpuState:
    """What the drop bookkeeping reads of a SimState, on the CPU (the sim may live on a GPU)."""

    qpos: torch.Tensor
    root_quat: torch.Tensor
    root_height: torch.Tensor
    joint_pos: torch.Tensor
    lin_speed: torch.Tensor
    ang_speed: torch.Tensor
    joint_speed: torch.Tensor
    unstable: torch.Tensor

    @classmethod
    def of(cls, st: SimState) -> "CpuState":
        return cls(
            qpos=st.qpos.cpu(),
            root_quat=st.root_quat.cpu(),
            root_height=st.root_pos[:, 2].cpu(),
            joint_pos=st.joint_pos.cpu(),
            lin_speed=st.root_lin_vel.norm(dim=1).cpu(),
            ang_speed=st.root_ang_vel.norm(dim=1).cpu(),
            joint_speed=st.joint_vel.abs().amax(dim=1).cpu(),
            unstable=st.unstable.cpu(),
        )


class RestDetector:
    """Per-world at-rest bookkeeping in policy steps (thresholds of SettleConfig)."""

    def __init__(self, n: int, cfg: SettleConfig, policy_dt: float):
        self.cfg = cfg
        self.rest_steps = max(1, math.ceil(cfg.rest_time / policy_dt - 1e-9))
        self.max_steps = max(1, math.ceil(cfg.max_time / policy_dt - 1e-9))
        self.age = torch.zeros(n, dtype=torch.long)
        self.calm = torch.zeros(n, dtype=torch.long)

    def restart(self, ids: torch.Tensor) -> None:
        self.age[ids] = 0
        self.calm[ids] = 0

    def update(self, state: CpuState) -> tuple[torch.Tensor, torch.Tensor]:
        """After a step: (at rest [n], timed out [n])."""
        c = self.cfg
        quiet = (state.lin_speed < c.lin_vel) & (state.ang_speed < c.ang_vel) & (state.joint_speed < c.joint_vel)
        self.age += 1
        self.calm = torch.where(quiet, self.calm + 1, torch.zeros_like(self.calm))
        at_rest = self.calm >= self.rest_steps
        return at_rest, (self.age >= self.max_steps) & ~at_rest


@dataclass
class SettleResult:
    qpos: torch.Tensor  # [n, nq] float64, the state at rest (or at the time cap)
    settled: torch.Tensor  # [n] bool
    seconds: torch.Tensor  # [n] simulated time until rest


def settle(
    spec: RobotSpec,
    qpos: torch.Tensor,
    cfg: SettleConfig | None = None,
    setpoint: torch.Tensor | None = None,
    backend: str = "mujoco",
    **sim_options: Any,
) -> SettleResult:
    """Simulate poses [n, nq] with frozen gains until each is at rest (or the time cap).

    The joints hold `setpoint` [n, J] (default: the joint angles of qpos). Used
    for the artist poses and to check that a settled pose stays put; the
    generator runs the same procedure in a refilling pool.
    """
    cfg = cfg or SettleConfig()
    n = qpos.shape[0]
    sim = make_sim(spec, n, backend, **sim_options)
    lay = Layout(spec)
    qpos = qpos.to(torch.float64)
    hold = (qpos[:, lay.joint_qpos] if setpoint is None else setpoint).to(torch.float32)
    sim.reset(torch.arange(n), qpos, torch.zeros(n, lay.nv, dtype=torch.float64))
    sim.set_gain_scale(torch.full((n,), cfg.gain_scale))
    rest = RestDetector(n, cfg, spec.policy_dt)
    done = torch.zeros(n, dtype=torch.bool)
    settled = torch.zeros(n, dtype=torch.bool)
    final = qpos.clone()
    seconds = torch.full((n,), float("nan"))
    hold = hold.to(sim.device)
    while not done.all():
        st = CpuState.of(sim.step(hold))
        at_rest, timeout = rest.update(st)
        new = ~done & (at_rest | timeout | st.unstable)
        ok = new & at_rest & ~st.unstable
        final[new] = st.qpos[new].double()
        settled |= ok
        seconds[ok] = rest.age[ok].float() * spec.policy_dt
        done |= new
    return SettleResult(final, settled, seconds)
