"""Typed configuration: every section of the composed Hydra config as pydantic models.

One module per section (`robot`, `sim`, `env`, `reward`, `train`, `eval`, `render`,
`play`, `dataset`, `detector`), holding only models: they are the one source of every default. Hydra's
`conf/config.yaml` names the group defaults and the `hydra:` block; the values come
from `defaults()` (stored in Hydra's ConfigStore by the app), so no value is written
twice. `validate()` turns a composed config into `FallkitConfig`, so a wrong value is
one clear line naming the key before any work starts.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import Field, ValidationError, model_validator

from fallkit.config.dataset import DatasetConfig, SettleConfig
from fallkit.config.detector import DetectorConfig, PushTestConfig
from fallkit.config.env import DisturbanceConfig, DisturbanceRange, EnvConfig, InitialStateConfig, ObservationNoise
from fallkit.config.eval import EvalConfig
from fallkit.config.play import PlayConfig
from fallkit.config.render import RenderConfig
from fallkit.config.reward import BUILTIN_TERMS, RewardConfig
from fallkit.config.robot import RobotConfig
from fallkit.config.section import Section
from fallkit.config.sim import SimConfig
from fallkit.config.train import LevelReplayConfig, PPOConfig, SelfImitationConfig, TeachersConfig, TrainConfig
from fallkit.errors import ConfigError

__all__ = [
    "BUILTIN_TERMS", "ConfigError", "DatasetConfig", "DetectorConfig", "DisturbanceConfig", "DisturbanceRange",
    "EnvConfig", "EvalConfig", "FallkitConfig", "InitialStateConfig", "LevelReplayConfig", "Mode", "ObservationNoise",
    "PlayConfig", "PPOConfig", "PushTestConfig", "RenderConfig", "RewardConfig", "RobotConfig", "SelfImitationConfig",
    "SettleConfig",
    "SimConfig", "TeachersConfig", "TrainConfig", "defaults", "validate",
]  # fmt: skip

Mode = Literal["train", "list", "poses", "eval", "render", "export", "sim2sim", "play", "warmup", "detect"]


class FallkitConfig(Section):
    """The whole validated configuration of one run."""

    mode: Mode = "train"
    seed: int = 0
    checkpoint: str | None = Field(None, description="a trained policy (file or run dir) for eval/render/export")
    resume: str | None = Field(None, description="continue training from this checkpoint or run dir")
    experiment: str | None = Field(
        None, description="the paper experiment this run is a job of (set by experiment=<name>; fallkit.experiments)"
    )
    robot: RobotConfig
    sim: SimConfig = Field(default_factory=SimConfig)
    env: EnvConfig = Field(default_factory=EnvConfig)
    reward: RewardConfig = Field(default_factory=RewardConfig)
    eval: EvalConfig = Field(default_factory=EvalConfig)
    render: RenderConfig = Field(default_factory=RenderConfig)
    play: PlayConfig = Field(default_factory=PlayConfig)
    dataset: DatasetConfig = Field(default_factory=DatasetConfig)
    detector: DetectorConfig = Field(default_factory=DetectorConfig)
    train: TrainConfig = Field(default_factory=TrainConfig)

    @model_validator(mode="after")
    def _seek_needs_the_clock(self) -> "FallkitConfig":
        if self.train.prior == "seek" and not self.env.observe_blend:
            raise ValueError(
                "train.prior=seek blends by u(t), which the actor then must observe: set env.observe_blend=true "
                "or train.prior=hold|none"
            )
        needs_prior = [f"train.{k}" for k, on in (("fade_residual", self.train.fade_residual),
                                                  ("ppo.prior_coef", self.train.ppo.prior_coef > 0)) if on]  # fmt: skip
        if self.train.prior == "none" and needs_prior:
            raise ValueError(
                f"train.prior=none leaves no prior for {' and '.join(needs_prior)}: set train.fade_residual=false "
                "train.ppo.prior_coef=0 (the MLP alone, as train=paper does), or train.prior=hold|seek"
            )
        if self.train.fade_residual and not self.env.observe_blend:
            raise ValueError(
                "train.fade_residual fades the MLP into a prior by u(t): it needs env.observe_blend=true"
            )
        if self.train.fade_noise is not None and not self.train.fade_residual:
            raise ValueError(
                "train.fade_noise fades the exploration noise with the learned deviation: it needs "
                "train.fade_residual=true (or train.fade_noise=null)"
            )
        return self

    @model_validator(mode="after")
    def _weighted_impact_heads_unnormalised(self) -> "FallkitConfig":
        ppo = self.train.ppo
        if ppo.value_per_component and ppo.normalize_value and self.env.sensitivity_inputs.enabled:
            raise ValueError(
                "train.ppo.value_per_component with env.sensitivity_inputs scales each impact head by its observed "
                "w_c², which train.ppo.normalize_value's target statistics cannot follow: set normalize_value=false"
            )
        return self

    @model_validator(mode="after")
    def _relabel_needs_drawn_weights(self) -> "FallkitConfig":
        inputs = self.env.sensitivity_inputs
        if self.train.ppo.relabel_sensitivity and not (inputs.enabled and inputs.low < inputs.high):
            raise ValueError(
                "train.ppo.relabel_sensitivity prices the collected falls under other sensitivity weights, which "
                "the policy must observe: set env.sensitivity_inputs.enabled=true (with low < high)"
            )
        return self

    @model_validator(mode="after")
    def _teachers_need_drawn_weights(self) -> "FallkitConfig":
        runs, inputs = self.train.teachers.runs, self.env.sensitivity_inputs
        if runs and not (inputs.enabled and inputs.low < inputs.high):
            raise ValueError(
                "train.teachers: the policy imitates the teacher of the weight it draws, so it must draw and observe "
                "its weights: set env.sensitivity_inputs.enabled=true (with low < high), or train.teachers.runs=[]"
            )
        if len(runs) == 1:
            raise ValueError(
                "train.teachers.runs has one run: teachers at two or more weights of one component are blended by "
                "the drawn weight; to start from one trained policy use train.init_from=<run>"
            )
        return self

    @model_validator(mode="after")
    def _blend_within_the_episode(self) -> "FallkitConfig":
        if self.reward.blend_time > self.env.episode_length:
            raise ValueError(
                f"reward.blend_time={self.reward.blend_time:g} s is longer than env.episode_length="
                f"{self.env.episode_length:g} s, so u(t) would never reach 1 (paper: T_blend <= T): "
                "shorten reward.blend_time or lengthen env.episode_length"
            )
        return self

    @model_validator(mode="after")
    def _minibatches_fit_the_batch(self) -> "FallkitConfig":
        # an empty minibatch would fail deep inside the loss; train=quick asks for 16 of them
        samples, ppo = self.sim.num_envs * self.train.num_steps, self.train.ppo
        for name in ("num_minibatches", "late_num_minibatches"):
            count = getattr(ppo, name)
            if self.mode == "train" and count is not None and samples < 2 * count:
                raise ValueError(
                    f"train.ppo.{name}={count} leaves fewer than 2 samples per minibatch in a batch of {samples} "
                    f"(sim.num_envs={self.sim.num_envs} × train.num_steps={self.train.num_steps}): lower "
                    f"train.ppo.{name} or raise sim.num_envs"
                )
        return self

    @model_validator(mode="after")
    def _dynamics_randomised_on_mujoco(self) -> "FallkitConfig":
        r = self.env.randomization
        on = [n for n in ("mass", "joint_damping", "armature") if getattr(r, n).enabled]
        if on and self.sim.backend == "warp":
            raise ValueError(
                f"env.randomization.{on[0]}: randomised on sim=mujoco only so far (mujoco_warp would need its "
                f"derived constants per world); switch it off or use sim=mujoco"
            )
        return self


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
    msg = error["msg"].removeprefix("Value error, ")  # our validators' own words need no prefix
    return f"{key}: {msg}{shown}" if key else msg  # a check across sections names its keys itself


def defaults() -> dict[str, Any]:
    """Every default of FallkitConfig as plain data, without `robot` (Hydra's robot group fills it).

    The app stores this in Hydra's ConfigStore as the node `fallkit_defaults`, which
    `conf/config.yaml` lists first: the models are the one place a default is written.
    """
    return FallkitConfig(robot=RobotConfig(name="-")).model_dump(mode="json", exclude={"robot"})
