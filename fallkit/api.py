"""The public plugin API: the one module a plugin imports from fallkit.

Everything a robot, reward-term or sampler plugin needs is re-exported here;
every other fallkit module is private and may change without notice. The
plugin author's guide is docs/plugins.md; working examples are under plugins/.

A plugin registers names in its pyproject.toml, one entry-point group per kind:

    [project.entry-points."fallkit.robots"]
    myrobot = "my_package.robot:myrobot"          # () -> RobotSpec
    [project.entry-points."fallkit.rewards"]
    my_term = "my_package.rewards:my_term"        # (RewardContext) -> Tensor [N]
    [project.entry-points."fallkit.samplers"]
    my_sampler = "my_package.samplers:factory"    # factory(spec, **config) -> sampler

A robot is built with `make_robot_spec(...)`, or from a URDF with
`robot_from_urdf(...)`.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from fallkit import registry
from fallkit.errors import PluginError, RobotSpecError, URDFError

# Where each re-exported name lives. They are imported on first use (PEP 562's module __getattr__), so a
# robot plugin that needs only make_robot_spec or robot_from_urdf loads without torch: robot lookups, `--help`
# and every config error answer in about 2 s instead of 5. `from fallkit.api import X` works as before; the
# same imports under TYPE_CHECKING serve type checkers and editors (tests/test_registry.py keeps the two equal).
_LAZY: dict[str, tuple[str, ...]] = {
    "fallkit.env.rewards.context": ("RewardContext",),
    "fallkit.poses.checker": ("PoseChecker",),
    "fallkit.robots": ("get_robot", "list_robots"),
    "fallkit.robots.spec": ("ComponentSpec", "JointSpec", "RobotSpec", "make_robot_spec"),
    "fallkit.robots.urdf": ("URDFWarning", "robot_from_urdf", "urdf_to_mjcf"),
    "fallkit.rotations": ("quat_from_euler", "quat_mul"),
    "fallkit.sim": ("make_sim",),
    "fallkit.sim.base": ("BatchSim", "Layout", "SimState"),
}
_HOME = {name: module for module, names in _LAZY.items() for name in names}

if TYPE_CHECKING:
    from fallkit.env.rewards.context import RewardContext
    from fallkit.poses.checker import PoseChecker
    from fallkit.robots import get_robot, list_robots
    from fallkit.robots.spec import ComponentSpec, JointSpec, RobotSpec, make_robot_spec
    from fallkit.robots.urdf import URDFWarning, robot_from_urdf, urdf_to_mjcf
    from fallkit.rotations import quat_from_euler, quat_mul
    from fallkit.sim import make_sim
    from fallkit.sim.base import BatchSim, Layout, SimState


def __getattr__(name: str) -> Any:
    if name not in _HOME:
        raise AttributeError(f"module 'fallkit.api' has no attribute '{name}'")
    value = getattr(importlib.import_module(_HOME[name]), name)
    globals()[name] = value  # looked up once
    return value


def __dir__() -> list[str]:
    return sorted(__all__)


__all__ = [
    # robots
    "ComponentSpec",
    "JointSpec",
    "RobotSpec",
    "RobotSpecError",
    "URDFError",
    "URDFWarning",
    "get_robot",
    "list_robots",
    "make_robot_spec",
    "robot_from_urdf",
    "urdf_to_mjcf",
    # reward terms
    "RewardContext",
    "get_reward_term",
    # samplers and what they build states with
    "BatchSim",
    "Layout",
    "PoseChecker",
    "SimState",
    "get_sampler",
    "make_sim",
    "quat_from_euler",
    "quat_mul",
    # errors
    "PluginError",
]


def get_reward_term(name: str) -> Any:
    """The reward term function registered under `name` in `fallkit.rewards`."""
    return registry.load("fallkit.rewards", name)


def get_sampler(name: str) -> Any:
    """The sampler factory registered under `name` in `fallkit.samplers`."""
    return registry.load("fallkit.samplers", name)
