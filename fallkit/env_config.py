"""EnvConfig: episode, action, observation and sampler settings of FallEnv.

Kept apart from `fallkit.env` so that validating a config does not import TorchRL.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field, field_validator

from fallkit import registry
from fallkit.observations import ObservationNoise
from fallkit.samplers.disturbances import DisturbanceConfig
from fallkit.samplers.initial_state import InitialStateConfig

_SAMPLER_ROLES = ("initial_state", "disturbances")


class EnvConfig(BaseModel):
    """Episode, action and observation settings of FallEnv."""

    model_config = ConfigDict(extra="forbid")

    episode_length: float = Field(3.0, gt=0, description="T [s]: every episode is truncated after T")
    action_scale: float = Field(0.5, gt=0, description="[rad] per action unit: setpoint = nominal + action_scale·a")
    clip_setpoints: bool = Field(True, description="clip setpoints to the joint limits")
    poses: str = Field(
        "default", description="end-pose source: 'default' (the robot's dataset), a .npz dataset or a .yaml pose file"
    )
    pose_fraction: float = Field(
        1.0, gt=0, le=1, description="fraction of the training split used (dataset-size ablation)"
    )
    noise: ObservationNoise = Field(default_factory=ObservationNoise)
    initial_state: InitialStateConfig = Field(default_factory=InitialStateConfig)
    disturbances: DisturbanceConfig = Field(default_factory=DisturbanceConfig)
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
