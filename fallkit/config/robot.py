"""`robot:` — which registered robot, and its sensitivity weights."""

from __future__ import annotations

from pydantic import Field, field_validator

from fallkit.config.section import Section


class RobotConfig(Section):
    """Which registered robot, and sensitivity weights overriding its defaults.

    Hydra fills `robot=<name>` from the registered robots, with the robot's own
    weights, so `robot.sensitivity.head=8` changes one component (paper Sec. V-E).
    `fallkit.robots.robot_spec(config.robot)` turns this into the RobotSpec.
    """

    name: str
    sensitivity: dict[str, float] = Field(default_factory=dict, description="component -> sensitivity weight w_c")

    @field_validator("sensitivity")
    @classmethod
    def _non_negative(cls, value: dict[str, float]) -> dict[str, float]:
        bad = {k: v for k, v in value.items() if v < 0}
        if bad:
            raise ValueError(f"weights must be >= 0, got {bad}")
        return value
