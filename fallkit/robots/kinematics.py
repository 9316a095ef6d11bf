"""The robot's kinematic tree and the soles of its feet as plain data, for forward kinematics without MuJoCo.

The fall detector (fallkit.deploy.detector) runs on the robot's computer with numpy alone. To place
the centre of mass and the soles of the feet relative to the base from the joint encoders it needs
what the MuJoCo model holds: each body's frame relative to its parent, its hinge joints (axis,
anchor, reference angle), its mass and centre of mass, and the collision geometry of the feet.
`detector_export` reads them out of the compiled model once, as JSON-ready lists, together with
the detector's settings; `mode=export` writes that into policy.json and `mode=detect` builds its
detector from the same dict, so the robot and the evaluation run one detector.

Joints that are not actuated (not in the policy's joint list) are taken at their reference angle:
the robot cannot report them, and the built-in robots have none.
"""

from __future__ import annotations

import difflib
import itertools
import logging

import mujoco
import numpy as np

from fallkit.config.detector import DetectorConfig
from fallkit.errors import ConfigError
from fallkit.robots.spec import RobotSpec

FORMAT = 1  # the layout of the exported dict; FallDetector refuses others
log = logging.getLogger(__name__)


def detector_export(spec: RobotSpec, config: DetectorConfig) -> dict:
    """policy.json's `fall_detector`: settings, the feet, the joint names and the kinematic model."""
    m = spec.mj_model()
    feet = _feet(spec, m, config)
    return {
        "format": FORMAT,
        "robot": spec.name,
        "settings": config.exported(),
        "feet": feet,
        "joint_names": spec.joint_names,
        "gravity": float(-m.opt.gravity[2]),
        "bodies": kinematic_tree(spec),
        "soles": [sole_points(m, m.body(f).id) for f in feet],
    }


def exported_detector(spec: RobotSpec, config: DetectorConfig) -> dict | None:
    """`detector_export` for mode=export: None (with a warning) for a robot that names no feet when
    `detector.feet` is not set either, so that such a robot's policy still exports, without a detector."""
    if config.feet is None and not spec.disturbance_bodies.get("feet"):
        log.warning("robot '%s' names no feet (disturbance_bodies['feet']): exported without a fall detector; "
                    "set detector.feet=[<body>,...] to export one", spec.name)  # fmt: skip
        return None
    return detector_export(spec, config)


def _feet(spec: RobotSpec, m: mujoco.MjModel, config: DetectorConfig) -> list[str]:
    feet = config.feet if config.feet is not None else spec.disturbance_bodies.get("feet")
    if not feet:
        raise ConfigError(
            f"detector.feet: robot '{spec.name}' names no feet (its disturbance_bodies has no 'feet'); "
            "set detector.feet=[<body>,...]"
        )
    robot = set(_subtree_names(spec, m))
    for f in feet:
        if f not in robot:
            close = difflib.get_close_matches(f, sorted(robot), n=1)
            hint = f"did you mean '{close[0]}'?" if close else f"its bodies: {', '.join(sorted(robot))}"
            raise ConfigError(f"detector.feet: robot '{spec.name}' has no body '{f}'; {hint}")
    return list(feet)


def _subtree_names(spec: RobotSpec, m: mujoco.MjModel) -> list[str]:
    return [m.body(b).name for b in _subtree(m, m.body(spec.root_body).id)]


def _subtree(m: mujoco.MjModel, root: int) -> list[int]:
    """The root body and its descendants, parents before children (MuJoCo's body order)."""
    inside = {root}
    for b in range(root + 1, m.nbody):
        if m.body_parentid[b] in inside:
            inside.add(b)
    return sorted(inside)


def kinematic_tree(spec: RobotSpec) -> list[dict]:
    """Every body of the robot, parents first; the root's frame is the base frame (identity).

    Per body: name, parent (index into the list, -1 for the root), pos and quat (w, x, y, z) of its
    frame in the parent's at zero joint angles, mass [kg], com (centre of mass in its frame) and
    its hinge joints in MuJoCo's order of application: policy index, axis and anchor in the body's
    frame, and ref (the angle at which the joint is at its modelled frame, MuJoCo's qpos0).
    """
    m = spec.mj_model()
    bodies = _subtree(m, m.body(spec.root_body).id)
    index = {b: i for i, b in enumerate(bodies)}
    policy = {n: i for i, n in enumerate(spec.joint_names)}
    out = []
    for b in bodies:
        root = b == bodies[0]
        joints = []
        for j in range(m.body_jntadr[b], m.body_jntadr[b] + m.body_jntnum[b]):
            name = m.joint(j).name
            if m.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE and name in policy:
                joints.append({"name": name, "index": policy[name], "axis": m.jnt_axis[j].tolist(),
                               "anchor": m.jnt_pos[j].tolist(), "ref": float(m.qpos0[m.jnt_qposadr[j]])})  # fmt: skip
        out.append({
            "name": m.body(b).name,
            "parent": -1 if root else index[int(m.body_parentid[b])],
            "pos": [0.0, 0.0, 0.0] if root else m.body_pos[b].tolist(),
            "quat": [1.0, 0.0, 0.0, 0.0] if root else m.body_quat[b].tolist(),
            "mass": float(m.body_mass[b]),
            "com": m.body_ipos[b].tolist(),
            "joints": joints,
        })  # fmt: skip
    return out


def sole_points(m: mujoco.MjModel, body: int) -> dict:
    """The points of a foot's collision geoms that can touch flat ground, in the foot's frame.

    Each point has a radius: the ground contact lies `radius` below it (spheres, capsule ends) or at
    it (box corners, cylinder rims, the corners of other shapes' bounding boxes). The detector takes
    the lowest of them as the ground and those near it as the support.
    """
    points, radii = [], []
    for g in range(m.body_geomadr[body], m.body_geomadr[body] + m.body_geomnum[body]):
        if m.geom_contype[g] == 0 and m.geom_conaffinity[g] == 0:
            continue  # visual only
        rot = np.zeros(9)
        mujoco.mju_quat2Mat(rot, m.geom_quat[g])
        local, radius = _geom_points(m, g)
        points.extend((m.geom_pos[g] + local @ rot.reshape(3, 3).T).tolist())
        radii.extend([radius] * len(local))
    if not points:
        raise ConfigError(f"detector.feet: body '{m.body(body).name}' has no collision geom to stand on")
    return {"body": m.body(body).name, "points": points, "radius": radii}


def _geom_points(m: mujoco.MjModel, g: int) -> tuple[np.ndarray, float]:
    """(points in the geom's frame [k, 3], radius) standing for the geom's surface against a plane."""
    t, size = m.geom_type[g], m.geom_size[g]
    if t == mujoco.mjtGeom.mjGEOM_SPHERE:
        return np.zeros((1, 3)), float(size[0])
    if t == mujoco.mjtGeom.mjGEOM_CAPSULE:
        return np.array([[0.0, 0.0, -size[1]], [0.0, 0.0, size[1]]]), float(size[0])
    if t == mujoco.mjtGeom.mjGEOM_CYLINDER:
        angle = np.linspace(0.0, 2 * np.pi, 8, endpoint=False)
        rim = np.stack([size[0] * np.cos(angle), size[0] * np.sin(angle), np.zeros(8)], axis=1)
        return np.concatenate([rim + [0.0, 0.0, -size[1]], rim + [0.0, 0.0, size[1]]]), 0.0
    if t == mujoco.mjtGeom.mjGEOM_BOX:
        half = size[:3]
        centre = np.zeros(3)
    else:  # ellipsoid, mesh, …: the corners of the local bounding box
        centre, half = m.geom_aabb[g, :3], m.geom_aabb[g, 3:]
    corners = np.array(list(itertools.product((-1.0, 1.0), repeat=3)))
    return centre + corners * half, 0.0
