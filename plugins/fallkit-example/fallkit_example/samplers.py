"""An initial-state sampler: falls that begin standing, with a push.

fallkit's default (paper Table II) starts every fall already tipping, from
random joint angles. This one starts the robot upright in its nominal pose and
pushes it, like a robot shoved while standing. Select it for the
`initial_state` role and narrow the tilt:

    python -m fallkit env.samplers.initial_state=standing_push env.initial_state.roll_pitch_deg=5

The environment calls the factory with the robot and the settings under
`env.initial_state` (InitialStateConfig's fields), then `sample(n, generator)`
at every reset.
"""

from __future__ import annotations

import math

import torch

from fallkit.api import Layout, PoseChecker, RobotSpec, quat_from_euler, quat_mul


class StandingPush:
    """Upright nominal pose, tilt uniform in ±roll_pitch_deg, horizontal push up to root_lin_vel."""

    def __init__(
        self,
        spec: RobotSpec,
        roll_pitch_deg: float = 5.0,
        random_yaw: bool = True,
        root_lin_vel: float = 2.0,
        root_ang_vel: float = 0.5,
        joint_vel: float = 0.5,
        clearance: float = 0.005,
        **not_used: object,  # Table II settings without meaning here (joint_spread): the pose is nominal
    ):
        self.spec = spec
        self.checker = PoseChecker(spec)
        self.layout: Layout = self.checker.layout
        self.tilt = math.radians(roll_pitch_deg)
        self.random_yaw = random_yaw
        self.push, self.spin, self.joint_vel, self.clearance = root_lin_vel, root_ang_vel, joint_vel, clearance

    def sample(self, n: int, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        """n states in MuJoCo layout: qpos [n, nq], qvel [n, nv], float64 (what the simulator resets to)."""
        f64 = dict(dtype=torch.float64)

        def uniform(*shape: int, half: float) -> torch.Tensor:
            return (2.0 * torch.rand(*shape, generator=generator, **f64) - 1.0) * half

        zero = torch.zeros(n, **f64)
        yaw = uniform(n, half=math.pi) if self.random_yaw else zero
        tilt = quat_from_euler(uniform(n, half=self.tilt), uniform(n, half=self.tilt), zero)
        quat = quat_mul(quat_from_euler(zero, zero, yaw), tilt)
        joints = torch.as_tensor(self.spec.nominal_q(), **f64).expand(n, -1)
        qpos = self.layout.qpos(torch.zeros(n, 3, **f64), quat, joints)
        qpos, _ = self.checker.place_on_ground(qpos, self.clearance)  # feet just above the floor

        heading = uniform(n, half=math.pi)
        speed = torch.rand(n, generator=generator, **f64) * self.push
        push = torch.stack([speed * heading.cos(), speed * heading.sin(), zero], dim=-1)  # world frame, horizontal
        qvel = self.layout.qvel(push, uniform(n, 3, half=self.spin), uniform(n, joints.shape[1], half=self.joint_vel))
        return qpos, qvel


def standing_push(spec: RobotSpec, **config: object) -> StandingPush:
    """Entry point `standing_push` of group fallkit.samplers: factory(spec, **env.initial_state)."""
    return StandingPush(spec, **config)
