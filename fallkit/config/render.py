"""`render:` — videos of paired falls (mode=render)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, field_validator

from fallkit.config.section import Section


class RenderConfig(Section):
    """Video options of `mode=render` (falls come from `eval`: seed, poses, seconds)."""

    format: Literal["mp4", "gif", "both"] = "mp4"
    falls: int = Field(1, gt=0, description="falls rendered one after another, each from a new initial state")
    fps: float = Field(25.0, gt=0, description="frames per simulated second (at most the policy rate)")
    width: int = Field(320, ge=16, description="pixels per panel")
    height: int = Field(240, ge=16, description="pixels")
    distance: float = Field(2.2, gt=0, description="camera distance [m]")
    force_scale: float = Field(0.3, gt=0, description="arrow length [m] of a contact force equal to the robot's weight")

    @field_validator("width", "height")
    @classmethod
    def _macro_block(cls, v: int) -> int:
        if v % 16:
            raise ValueError(f"must be a multiple of 16 (video codecs), got {v}")
        return v
