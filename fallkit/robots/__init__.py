"""Robots: the RobotSpec model, URDF import and the built-in robots (biped20).

Robots are found through the entry-point group `fallkit.robots`, fallkit's own
exactly like a plugin's; `get_robot(name)` loads and checks one.
"""

from __future__ import annotations

from typing import Any

from fallkit import registry
from fallkit.config.robot import RobotConfig
from fallkit.robots.spec import RobotSpec

GROUP = "fallkit.robots"


@registry.validator(GROUP)
def _check_robot(value: Any) -> tuple[Any, str | None]:
    spec = value() if callable(value) and not isinstance(value, RobotSpec) else value
    if not isinstance(spec, RobotSpec):
        return value, f"expected a RobotSpec (or a callable returning one), got {type(spec).__name__}"
    return spec, None


def get_robot(name: str) -> RobotSpec:
    """The RobotSpec registered under `name` in the `fallkit.robots` entry-point group."""
    return registry.load(GROUP, name)


def list_robots() -> list[str]:
    """Names of all registered robots."""
    return registry.names(GROUP)


def robot_spec(config: RobotConfig) -> RobotSpec:
    """The RobotSpec a run's `robot:` section names, with its sensitivity weights applied."""
    return get_robot(config.name).with_sensitivity(config.sensitivity)
