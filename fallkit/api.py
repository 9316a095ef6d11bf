"""The public plugin API: the one module a plugin imports from fallkit.

Everything a robot, reward-term or sampler plugin needs is re-exported here;
every other fallkit module is private and may change without notice.

A robot plugin registers, in its pyproject.toml:

    [project.entry-points."fallkit.robots"]
    myrobot = "my_package.robot:myrobot"     # a callable returning a RobotSpec

and builds its spec with `make_robot_spec(...)` (or `RobotSpec(...)`).
"""

from __future__ import annotations

from fallkit.registry import PluginError
from fallkit.robots.spec import ComponentSpec, JointSpec, RobotSpec, RobotSpecError, make_robot_spec

__all__ = [
    "ComponentSpec",
    "JointSpec",
    "PluginError",
    "RobotSpec",
    "RobotSpecError",
    "get_robot",
    "list_robots",
    "make_robot_spec",
]


def get_robot(name: str) -> RobotSpec:
    """The RobotSpec registered under `name` in the `fallkit.robots` entry-point group."""
    from fallkit import registry

    return registry.load("fallkit.robots", name)


def list_robots() -> list[str]:
    """Names of all registered robots."""
    from fallkit import registry

    return registry.names("fallkit.robots")
