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

from typing import Any

from fallkit import registry
from fallkit.env.rewards.context import RewardContext
from fallkit.errors import PluginError, RobotSpecError, URDFError
from fallkit.poses.checker import PoseChecker
from fallkit.robots import get_robot, list_robots
from fallkit.robots.spec import ComponentSpec, JointSpec, RobotSpec, make_robot_spec
from fallkit.robots.urdf import URDFWarning, robot_from_urdf, urdf_to_mjcf
from fallkit.rotations import quat_from_euler, quat_mul
from fallkit.sim import make_sim
from fallkit.sim.base import BatchSim, Layout, SimState

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
