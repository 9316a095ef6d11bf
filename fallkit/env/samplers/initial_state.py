"""Initial falling states (paper Sec. IV-D, Table II).

Root roll and pitch uniform in ±30° (pitch then roll), random heading (the
policy is yaw-invariant through the path frame, so heading only adds variety),
joint positions uniform within limits with self-colliding draws rejected, the
lowest geom placed just above the ground, and uniform velocities:
root linear ±2.0 m/s, root angular ±0.5 rad/s, joints ±0.5 rad/s, per axis.
"""

from __future__ import annotations

import math

import torch

from fallkit.config import InitialStateConfig
from fallkit.poses.checker import PoseChecker
from fallkit.robots.spec import RobotSpec
from fallkit.rotations import quat_from_euler, quat_mul


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
        zero = torch.zeros_like(yaw)
        # pitch first, then roll (both about world axes), then the heading
        tilt_q = quat_mul(quat_from_euler(roll, zero, zero), quat_from_euler(zero, pitch, zero))
        quat = quat_mul(quat_from_euler(zero, zero, yaw), tilt_q)
        qpos, _ = self.checker.on_ground(quat, joints, c.clearance)
        qvel = self.layout.qvel(
            uniform(n, 3, half=c.root_lin_vel), uniform(n, 3, half=c.root_ang_vel), uniform(n, len(joints[0]), half=c.joint_vel)
        )
        return qpos, qvel


def initial_state(spec: RobotSpec, **config) -> InitialStateSampler:
    """Entry point `initial_state` of group fallkit.samplers."""
    return InitialStateSampler(spec, InitialStateConfig(**config))
