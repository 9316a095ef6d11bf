"""Initial falling states (paper Sec. IV-D, Table II).

Root roll and pitch uniform in ±30° (pitch then roll), random heading (the
policy is yaw-invariant through the path frame, so heading only adds variety),
joint positions uniform within limits with self-colliding draws rejected, the
lowest geom placed just above the ground, and uniform velocities:
root linear ±2.0 m/s, root angular ±0.5 rad/s, joints ±0.5 rad/s, per axis.
"""

from __future__ import annotations

import math
from typing import Protocol

import torch

from fallkit.config import InitialStateConfig
from fallkit.poses.checker import PoseChecker
from fallkit.robots.spec import RobotSpec


class InitialStateSampler:
    """Draws MuJoCo-layout (qpos, qvel) batches of falling initial states."""

    def __init__(self, spec: RobotSpec, config: InitialStateConfig | None = None, checker: PoseChecker | None = None):
        self.spec = spec
        self.config = config or InitialStateConfig()
        self.checker = checker or PoseChecker(spec)
        self.layout = self.checker.layout

    def sample(self, n: int, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        """n initial states: qpos [n, nq], qvel [n, nv], float64."""
        c = self.config
        g = generator

        def uniform(*shape: int, half: float) -> torch.Tensor:
            return (2.0 * torch.rand(*shape, generator=g, dtype=torch.float64) - 1.0) * half

        joints = self.checker.sample_joints(n, g, spread=c.joint_spread)
        tilt = math.radians(c.roll_pitch_deg)
        pitch, roll = uniform(n, half=tilt), uniform(n, half=tilt)
        yaw = uniform(n, half=math.pi) if c.random_yaw else torch.zeros(n, dtype=torch.float64)
        quat = _root_quat(roll, pitch, yaw)
        qpos, _ = self.checker.on_ground(quat, joints, c.clearance)
        qvel = self.layout.qvel(
            uniform(n, 3, half=c.root_lin_vel), uniform(n, 3, half=c.root_ang_vel), uniform(n, len(joints[0]), half=c.joint_vel)
        )
        return qpos, qvel


class SamplesInitialStates(Protocol):
    """What the registered initial-state sampler provides (`env.samplers.initial_state`, docs/env.md)."""

    def sample(self, n: int, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]: ...


class InitialStateStock:
    """Initial states drawn ahead, in bulk, for training's restarts.

    A training step restarts a few worlds at a time (about 1 in 150: an episode is 150 steps), and each
    `sample` call costs its self-collision and ground checks whatever its size: 1.7 ms for 1 to 32 states,
    against 27-44 µs a state in batches of 64 and more (biped20, this project's CPU). So `take` hands out
    states drawn `chunk` at a time by any sampler with `sample(n, generator)` (a plugin's too). The states are
    the sampler's, in the order it drew them; what is left in stock is part of the env's run state, so a
    resumed run restarts its worlds from the same states.
    """

    def __init__(self, sampler: SamplesInitialStates, chunk: int):
        self.sampler, self.chunk = sampler, chunk
        self.qpos = self.qvel = None  # [k, nq], [k, nv] float64: drawn and not yet taken

    def take(self, n: int, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        """The next n states (qpos [n, nq], qvel [n, nv], float64), drawing `chunk` more (or n) when short."""
        have = 0 if self.qpos is None else len(self.qpos)
        if have < n:
            qpos, qvel = self.sampler.sample(max(self.chunk, n - have), generator)
            self.qpos = qpos if self.qpos is None else torch.cat((self.qpos, qpos))
            self.qvel = qvel if self.qvel is None else torch.cat((self.qvel, qvel))
        out = self.qpos[:n], self.qvel[:n]
        self.qpos, self.qvel = self.qpos[n:], self.qvel[n:]
        return out

    def state(self) -> tuple[torch.Tensor, torch.Tensor] | None:
        return None if self.qpos is None else (self.qpos.clone(), self.qvel.clone())

    def load(self, state: tuple[torch.Tensor, torch.Tensor] | None) -> None:
        self.qpos, self.qvel = (None, None) if state is None else (state[0].clone(), state[1].clone())


def _root_quat(roll: torch.Tensor, pitch: torch.Tensor, yaw: torch.Tensor) -> torch.Tensor:
    """Rz(yaw) ⊗ Rx(roll) ⊗ Ry(pitch): pitch first, then roll (both about world axes), then the heading.

    The Hamilton products of these one-axis rotations written out (their other terms are exact
    zeros): the same bits as composing `quat_from_euler`s with `quat_mul`, in a tenth of the tensor
    operations — this runs for the worlds that restart at every training step.
    """
    cr, sr, cp, sp = torch.cos(0.5 * roll), torch.sin(0.5 * roll), torch.cos(0.5 * pitch), torch.sin(0.5 * pitch)
    cy, sy = torch.cos(0.5 * yaw), torch.sin(0.5 * yaw)
    w, x, y, z = cr * cp, sr * cp, cr * sp, sr * sp  # Rx(roll) ⊗ Ry(pitch)
    return torch.stack((cy * w - sy * z, cy * x - sy * y, cy * y + sy * x, cy * z + sy * w), -1)


def initial_state(spec: RobotSpec, **config) -> InitialStateSampler:
    """Entry point `initial_state` of group fallkit.samplers."""
    return InitialStateSampler(spec, InitialStateConfig(**config))
