"""`sim:` — simulator backend and size."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from fallkit.config.section import Section


class SimConfig(Section):
    """Simulator backend and size."""

    backend: Literal["mujoco", "warp"] = "mujoco"
    num_envs: int = Field(256, gt=0, description="parallel worlds")
    threads: int = Field(0, ge=0, description="mujoco backend: CPU threads, 0 = this process's share of the cores (fallkit.machine)")
    device: str = Field("cpu", description="warp backend: auto | cpu | cuda:N")
    nconmax: int | None = Field(None, gt=0, description="warp backend: contacts per world, pooled over worlds (None = from the robot)")
    njmax: int | None = Field(None, gt=0, description="warp backend: constraint rows per world (None = from the robot)")
    max_speed: float = Field(200.0, gt=0, description="[m/s or rad/s] above this a world counts as unstable")

    @model_validator(mode="after")
    def _device_needs_warp(self) -> "SimConfig":
        # MuJoCo C runs on the CPU only: a GPU asked of it would be silently ignored
        if self.backend == "mujoco" and self.device != "cpu":
            raise ValueError(
                f"device={self.device} needs the warp backend (the mujoco backend runs on the CPU): "
                f"add sim=warp, or drop sim.device"
            )
        return self
