"""Typed configuration: the composed Hydra config, validated with pydantic.

Hydra composes `fallkit/conf/` (plus one `robot/<name>` node per registered
robot); `validate()` turns the result into these models so a wrong value is one
clear line naming the key, before any work starts. Each concept's own config
model lives next to its code; this module only assembles them.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from fallkit.env_config import EnvConfig
from fallkit.evaluate import EvalConfig
from fallkit.render import RenderConfig
from fallkit.rewards.context import RewardConfig
from fallkit.samplers.end_poses import PosesConfig
from fallkit.train_config import TrainConfig


class ConfigError(ValueError):
    """An invalid configuration value; the message names the key."""


class RobotConfig(BaseModel):
    """Which registered robot, and sensitivity weights overriding its defaults."""

    model_config = ConfigDict(extra="forbid")

    name: str
    sensitivity: dict[str, float] = Field(default_factory=dict)

    def spec(self):  # -> RobotSpec
        from fallkit.api import get_robot

        bad = {k: v for k, v in self.sensitivity.items() if v < 0}
        if bad:
            raise ConfigError(f"robot.sensitivity: weights must be >= 0, got {bad}")
        return get_robot(self.name).with_sensitivity(self.sensitivity)


class SimConfig(BaseModel):
    """Simulator backend and size."""

    model_config = ConfigDict(extra="forbid")

    backend: Literal["mujoco", "warp"] = "mujoco"
    num_envs: int = Field(256, gt=0, description="parallel worlds")
    threads: int = Field(0, ge=0, description="mujoco backend: CPU threads, 0 = all cores")
    device: str = Field("cpu", description="warp backend: auto | cpu | cuda:N")
    nconmax: int | None = Field(None, gt=0, description="warp backend: contacts per world, pooled over worlds (None = from the robot)")
    njmax: int | None = Field(None, gt=0, description="warp backend: constraint rows per world (None = from the robot)")
    max_speed: float = Field(200.0, gt=0, description="[m/s or rad/s] above this a world counts as unstable")


Mode = Literal["train", "list", "poses", "eval", "render", "export"]


class FallkitConfig(BaseModel):
    """The whole validated configuration of one run."""

    model_config = ConfigDict(extra="forbid")

    mode: Mode = "train"
    seed: int = 0
    checkpoint: str | None = Field(None, description="a trained policy (file or run dir) for eval/render/export")
    resume: str | None = Field(None, description="continue training from this checkpoint or run dir")
    robot: RobotConfig
    sim: SimConfig = Field(default_factory=SimConfig)
    env: EnvConfig = Field(default_factory=EnvConfig)
    reward: RewardConfig = Field(default_factory=RewardConfig)
    eval: EvalConfig = Field(default_factory=EvalConfig)
    render: RenderConfig = Field(default_factory=RenderConfig)
    poses: PosesConfig = Field(default_factory=PosesConfig)
    train: "TrainConfig" = Field(default_factory=lambda: TrainConfig())


def validate(raw: dict[str, Any]) -> FallkitConfig:
    """Validate a resolved config dict; raise ConfigError naming every bad key."""
    try:
        return FallkitConfig.model_validate(raw)
    except ValidationError as exc:
        raise ConfigError("; ".join(_describe(e) for e in exc.errors())) from None


def _describe(error: dict[str, Any]) -> str:
    key = ".".join(str(p) for p in error["loc"])
    got = error.get("input")
    shown = "" if isinstance(got, dict) else f" (got {got!r})"
    return f"{key}: {error['msg']}{shown}"
