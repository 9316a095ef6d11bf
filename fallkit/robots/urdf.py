"""URDF import: turn the robot description a vendor ships into a fallkit robot.

`robot_from_urdf(name, urdf, joints=..., components=...)` returns a RobotSpec;
`urdf_to_mjcf(urdf, ...)` is the conversion step alone. MuJoCo's own URDF
compiler does the work (`mujoco.MjSpec.from_string` on the URDF, then
`MjSpec.fuse_static`); this module only prepares the URDF for it and checks
what MuJoCo would reject with a message that names nothing useful:

- meshes: `package://pkg/...` (found next to the URDF's ancestors, on
  ROS_PACKAGE_PATH or in `package_dirs`), `file://` and relative paths are
  resolved; a missing collision mesh is an error. Collision meshes MuJoCo cannot
  read (anything but .stl/.obj/.msh, e.g. Collada .dae) are replaced by a
  readable file of the same name next to them if there is one, else by ONE box
  per link with the link's mass and inertia (the "equivalent inertia box"),
  with a warning. Visual elements are dropped: fallkit simulates and renders the
  collision geometry.
- inertias MuJoCo refuses (not positive definite, or violating A + B >= C) are
  replaced by the isotropic inertia of the same trace, with a warning naming
  the link. That is MuJoCo's own `balanceinertia` rule, extended to
  non-positive eigenvalues (go1's 1 mg `base` link has such an inertia).
- floating base: the root link (or `root_link`, when the URDF hangs the robot
  under dummy links joined by fixed joints) is written without joints, so
  RobotSpec adds its free joint "root".
- static links (fixed joints: sensor frames, rotor housings, feet) are fused
  into their parents by MuJoCo, except the links fallkit names (components,
  disturbance bodies, `keep_bodies`), which stay bodies.
- joint effort limits are dropped from the MJCF: the torque limit of each
  actuated joint is the one in its JointSpec (one source of truth).

The MJCF is written with its collision meshes into a content-addressed folder
of the cache (`$FALLKIT_CACHE_DIR`, else `$XDG_CACHE_HOME/fallkit`, else
`~/.cache/fallkit`): `urdf/<name>-<hash>/<name>.xml`, with mesh paths relative
to it, so the same URDF gives the same MJCF text (and `RobotSpec.model_hash`)
on every machine. Conversion takes milliseconds for primitive-only robots and
is redone on each call; an existing output folder is reused.

A URDF that cannot be used raises `URDFError` naming the file and the element.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from pathlib import Path

import mujoco

from fallkit.errors import URDFError
from fallkit.robots.spec import ComponentSpec, JointSpec, RobotSpec, make_robot_spec
from fallkit.robots.urdf_mjcf import convert
from fallkit.robots.urdf_tree import UrdfTree, URDFWarning, read_urdf

__all__ = ["ACTUATED_TYPES", "URDFWarning", "robot_from_urdf", "urdf_to_mjcf"]

ACTUATED_TYPES = ("revolute", "continuous")  # URDF joints that become MuJoCo hinges


def robot_from_urdf(
    name: str,
    urdf: str | Path,
    *,
    joints: Iterable[JointSpec],
    components: Mapping[str, ComponentSpec] | None = None,
    nominal_pose: Mapping[str, float] | None = None,
    disturbance_bodies: Mapping[str, list[str]] | None = None,
    root_link: str | None = None,
    armature: Mapping[str, float] | None = None,
    keep_bodies: Iterable[str] = (),
    package_dirs: Mapping[str, str | Path] | None = None,
    edit: Callable[[mujoco.MjSpec], None] | None = None,
    cache_dir: str | Path | None = None,
    policy_hz: float = 50.0,
    timestep: float = 0.005,
    friction: float = 1.0,
) -> RobotSpec:
    """A RobotSpec for the robot described by `urdf`.

    joints: the actuated joints in policy order, with PD gains and torque
        limits; each must be a revolute or continuous joint of the URDF.
    components: named groups of links with sensitivity weights; default: one
        component "body" holding every body of the converted model, weight 1.
    armature: joint -> reflected rotor inertia [kg·m²] (URDF has no such field).
    edit: called with the MjSpec of the imported robot before static links are
        fused, to add what the URDF lacks (geoms, sites) with MuJoCo's own API.
    The other arguments are RobotSpec's fields or `urdf_to_mjcf`'s.
    """
    joints = list(joints)
    tree = read_urdf(Path(urdf))
    _check_joints(tree, joints)
    named = _named_bodies(keep_bodies, disturbance_bodies, components)
    mjcf = convert(tree, root_link, named, armature, package_dirs, edit, cache_dir, name)
    spec = mujoco.MjSpec.from_file(str(mjcf))
    root = _root_body(spec)
    if components is None:
        components = {"body": ComponentSpec(bodies=[b.name for b in spec.bodies if b.name != "world"], weight=1.0)}
    return make_robot_spec(
        name,
        mjcf=mjcf,
        root_body=root,
        joints=joints,
        components=dict(components),
        nominal_pose=dict(nominal_pose or {}),
        disturbance_bodies=dict(disturbance_bodies or {}),
        policy_hz=policy_hz,
        timestep=timestep,
        friction=friction,
    )


def urdf_to_mjcf(
    urdf: str | Path,
    *,
    root_link: str | None = None,
    keep_bodies: Iterable[str] = (),
    armature: Mapping[str, float] | None = None,
    package_dirs: Mapping[str, str | Path] | None = None,
    edit: Callable[[mujoco.MjSpec], None] | None = None,
    cache_dir: str | Path | None = None,
    name: str | None = None,
) -> Path:
    """Convert `urdf` to an MJCF of the robot alone (no floor, actuators or free joint).

    Returns the path of the MJCF in the cache; see the module docstring for
    what is resolved, repaired or refused.
    """
    named = _named_bodies(keep_bodies)
    return convert(read_urdf(Path(urdf)), root_link, named, armature, package_dirs, edit, cache_dir, name)


def _check_joints(tree: UrdfTree, joints: list[JointSpec]) -> None:
    """Every actuated joint must be a revolute or continuous joint of the URDF; a revolute one without limits warns."""
    movable = {n: j.get("type") for n, j in tree.joints.items()}
    for j in joints:
        if j.name not in movable:
            raise URDFError(
                f"{tree.path}: joints: no joint '{j.name}' in the URDF; its revolute joints are "
                f"{sorted(n for n, t in movable.items() if t in ACTUATED_TYPES)}"
            )
        if movable[j.name] not in ACTUATED_TYPES:
            raise URDFError(
                f"{tree.path}: joints: joint '{j.name}' is {movable[j.name]}; "
                "only revolute and continuous joints can be actuated"
            )
        limit = tree.joints[j.name].find("limit")
        if movable[j.name] == "revolute" and (limit is None or limit.get("lower") is None or limit.get("upper") is None):
            tree.warn(
                f"joint '{j.name}' is revolute without <limit lower=… upper=…>: it is simulated unlimited and end poses "
                "and initial states sample it over ±π; add the limits (or declare it continuous if it truly turns freely)"
            )


def _named_bodies(
    keep_bodies: Iterable[str],
    disturbance_bodies: Mapping[str, list[str]] | None = None,
    components: Mapping[str, ComponentSpec] | None = None,
) -> dict[str, str]:
    """The links fallkit names (kept as bodies when static links are fused) -> where they were named."""
    named = {b: "keep_bodies" for b in keep_bodies}
    for role, bodies in (disturbance_bodies or {}).items():
        named.update({b: f"disturbance_bodies.{role}" for b in bodies})
    for comp, c in (components or {}).items():
        named.update({b: f"components.{comp}" for b in c.bodies})
    return named


def _root_body(spec: mujoco.MjSpec) -> str:
    tops = [b for b in spec.worldbody.bodies]
    if len(tops) != 1:
        raise URDFError(f"converted model has {len(tops)} top-level bodies, expected 1")
    return tops[0].name
