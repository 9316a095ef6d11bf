"""`env:` — episode, action, observation noise, initial states (Table II) and disturbances (Table IV).

Kept apart from `fallkit.env` so that validating a config does not import TorchRL.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field, field_validator, model_validator

from fallkit import registry
from fallkit.config.section import Section

_SAMPLER_ROLES = ("initial_state", "disturbances")


class ObservationNoise(Section):
    """Std of the Gaussian noise on the actor's measured inputs (legged_gym's levels)."""

    scale: float = Field(1.0, ge=0, description="multiplies every std below; 0 switches noise off")
    root_quat: float = Field(0.05, ge=0, description="per quaternion component")
    root_lin_vel: float = Field(0.1, ge=0, description="[m/s]")
    root_ang_vel: float = Field(0.2, ge=0, description="[rad/s]")
    joint_pos: float = Field(0.01, ge=0, description="[rad]")
    joint_vel: float = Field(1.5, ge=0, description="[rad/s]")


class InitialStateConfig(Section):
    """Ranges of paper Table II (half-widths of uniform distributions)."""

    roll_pitch_deg: float = Field(30.0, ge=0, le=180)
    random_yaw: bool = True
    root_lin_vel: float = Field(2.0, ge=0, description="[m/s] per axis, world frame")
    root_ang_vel: float = Field(0.5, ge=0, description="[rad/s] per axis, root frame")
    joint_vel: float = Field(0.5, ge=0, description="[rad/s] per joint")
    joint_spread: float = Field(
        1.0, gt=0, le=1.0, description="fraction of each joint's range around the nominal pose (1 = full range)"
    )
    clearance: float = Field(0.005, ge=0, description="[m] gap between the lowest geom and the floor")


class DisturbanceRange(Section):
    """Magnitudes and durations for the bodies of one role."""

    force: float = Field(5.0, ge=0, description="[N] max |force| per axis")
    torque: float = Field(0.25, ge=0, description="[N·m] max |torque| per axis")
    on_time: tuple[float, float] = Field((0.25, 2.0), description="[s] range of an 'on' period")
    off_time: tuple[float, float] = Field((1.0, 3.0), description="[s] range of an 'off' period")

    @model_validator(mode="after")
    def _ordered(self) -> "DisturbanceRange":
        for name in ("on_time", "off_time"):
            lo, hi = getattr(self, name)
            if not 0 < lo <= hi:
                raise ValueError(f"{name}: need 0 < min <= max, got [{lo}, {hi}]")
        return self


def _table_iv() -> dict[str, DisturbanceRange]:
    short, long = DisturbanceRange(), DisturbanceRange(on_time=(2.0, 10.0))
    return {"hips": short, "feet": short, "elbows": short, "pelvis": long, "head": long}


class DisturbanceConfig(Section):
    """Paper Table IV by role."""

    enabled: bool = True
    roles: dict[str, DisturbanceRange] = Field(default_factory=_table_iv)


class RandomRange(Section):
    """A quantity drawn uniformly in [low, high] per episode, when enabled."""

    enabled: bool = False
    low: float = Field(gt=0)
    high: float = Field(gt=0)

    @model_validator(mode="after")
    def _ordered(self) -> "RandomRange":
        if self.low > self.high:
            raise ValueError(f"low {self.low} > high {self.high}")
        return self


class RandomizationConfig(Section):
    """Per-episode domain randomisation for sim-to-real (each off by default; fallkit.env.randomization).
    The critic observes the friction; evaluation switches every one off."""

    friction: RandomRange = Field(
        default_factory=lambda: RandomRange(low=0.5, high=1.25),
        description="sliding friction of every contact (legged_gym-like range)",
    )
    gain_scale: RandomRange = Field(
        default_factory=lambda: RandomRange(low=0.8, high=1.2),
        description="PD stiffness and damping × this: actuator strength",
    )
    action_delay: float = Field(
        0.0, ge=0, le=1, description="chance that an episode applies every action one policy step late (0 = never)"
    )
    mass: RandomRange = Field(
        default_factory=lambda: RandomRange(low=0.8, high=1.2),
        description="every link's mass and rotational inertia × its own factor: payload, CAD error (sim=mujoco)",
    )
    joint_damping: RandomRange = Field(
        default_factory=lambda: RandomRange(low=0.5, high=2.0),
        description="every joint's viscous damping × this: gearbox friction (sim=mujoco)",
    )
    armature: RandomRange = Field(
        default_factory=lambda: RandomRange(low=0.8, high=1.2),
        description="every joint's armature (reflected rotor inertia) × this (sim=mujoco)",
    )


class SensitivityInputs(Section):
    """The components' sensitivity weights as inputs of the actor and critic (beyond the paper, which fixes
    them at training time; docs/sensitivity_inputs.md). Off by default: it has to pay for itself."""

    enabled: bool = Field(
        False,
        description="the actor and critic observe ln w_c of every component, so robot.sensitivity.<c>=w at "
        "evaluation, render, sim2sim, play or on the robot changes what the same policy does",
    )
    low: float = Field(
        0.2, gt=0, description="each episode draws w_c = robot weight × f_c, ln f_c uniform in [ln low, ln high]"
    )
    high: float = Field(
        5.0, gt=0, description="per component, independently; low = high = 1: the robot's own weights, nothing drawn"
    )
    draw: Literal["each", "one"] = Field(
        "each",
        description="each: every component's factor is drawn; one: one component, chosen uniformly per episode, "
        "is drawn and the others keep the robot's weights (each episode then says what one weight changes)",
    )
    components: list[str] | None = Field(
        None,
        min_length=1,
        description="the components whose weights are drawn, and so can be set at run time (e.g. [head,battery]); "
        "the others keep the robot's weights in training, their inputs constant; null = every component",
    )

    @model_validator(mode="after")
    def _ordered(self) -> "SensitivityInputs":
        if self.low > self.high:
            raise ValueError(f"low {self.low} > high {self.high}")
        return self


class EnvConfig(Section):
    """Episode, action and observation settings of FallEnv."""

    episode_length: float = Field(3.0, gt=0, description="T [s]: every episode is truncated after T")
    action_scale: float = Field(0.5, gt=0, description="[rad] per action unit: setpoint = nominal + action_scale·a")
    clip_setpoints: bool = Field(True, description="clip setpoints to the joint limits")
    observe_blend: bool = Field(
        True,
        description="the actor observes u(t), the tracking blend of the time since the fall began (a clock the "
        "robot keeps); false feeds it a zero, as the paper's actor, which does not observe time",
    )
    observe_gravity: bool = Field(
        False,
        description="the actor (and critic) also observe the world up axis in the root frame and in the end pose's "
        "root frame, the two vectors the orientation reward compares (the quaternions stay observed too)",
    )
    poses: str = Field(
        "default", description="end-pose source: 'default' (the robot's dataset), a .npz dataset or a .yaml pose file"
    )
    pose_fraction: float = Field(
        1.0, gt=0, le=1, description="fraction of the training split used (dataset-size ablation)"
    )
    heading_end_poses: float = Field(
        0.0,
        ge=0,
        le=1,
        description="share of training episodes whose end pose is, of heading_candidates drawn uniformly, the one "
        "lying closest to where the fall heads (its capture point; fallkit.env.samplers.end_pose); 0 = every end "
        "pose drawn uniformly (the paper). Evaluation is unaffected: it resets to given falls and end poses",
    )
    heading_candidates: int = Field(8, ge=2, description="end poses drawn per heading choice (heading_end_poses)")
    noise: ObservationNoise = Field(default_factory=ObservationNoise)
    initial_state: InitialStateConfig = Field(default_factory=InitialStateConfig)
    disturbances: DisturbanceConfig = Field(default_factory=DisturbanceConfig)
    randomization: RandomizationConfig = Field(default_factory=RandomizationConfig)
    sensitivity_inputs: SensitivityInputs = Field(default_factory=SensitivityInputs)
    samplers: dict[str, str] = Field(
        default_factory=lambda: {r: r for r in _SAMPLER_ROLES},
        description="sampler role -> registered sampler (group fallkit.samplers)",
    )

    @field_validator("samplers")
    @classmethod
    def _roles(cls, value: dict[str, str]) -> dict[str, str]:
        unknown = sorted(set(value) - set(_SAMPLER_ROLES))
        if unknown:
            raise ValueError(f"unknown sampler roles {unknown}; roles are {list(_SAMPLER_ROLES)}")
        registered = registry.names("fallkit.samplers")
        for role, name in value.items():
            if name not in registered:
                raise ValueError(f"{role}: '{name}' is not a registered sampler ({', '.join(registered) or 'none'})")
        return {**{r: r for r in _SAMPLER_ROLES}, **value}
