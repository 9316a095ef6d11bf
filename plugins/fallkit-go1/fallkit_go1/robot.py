"""Unitree Go1 (12 DoF, 13.1 kg) from example-robot-data's URDF, through fallkit's URDF import.

Only `fallkit.api` is used: this file is what a third party writes to add a robot.

Model (what the URDF gives, what this plugin adds):
- Collision geometry is the URDF's own primitives (trunk box, hip/rotor
  cylinders, thigh/calf boxes, 2 cm foot spheres). The URDF's trunk box ends at
  x = 0.188 m while the real face module (stereo cameras) reaches x = 0.30 m
  (trunk.dae); `_add_head` adds a massless box there as body "head" so the face
  has its own contact force.
- The dummy `base` link above `trunk` (1 mg, an inertia MuJoCo rejects) is
  dropped: `trunk` carries the floating base.
- Armature: reflected rotor inertia, I_rotor · N² with the URDF's rotor
  inertia 0.000111842 kg·m² and gear ratios 6 (hip, thigh) and 9 (knee).
- Gains kp 35 N·m/rad, kd 0.5 N·m·s/rad (the Go1 of MuJoCo Playground / mjlab);
  torque limits 23.7 N·m (hip, thigh) and 35.55 N·m (knee), the URDF's efforts.

Components and sensitivity weights (paper Sec. V-A; w_c scales a component's
contact force in the impact reward):

| component | bodies | w_c | why |
|---|---|---|---|
| head   | face module      | 4.0 | stereo cameras, the most fragile part |
| trunk  | trunk            | 2.0 | battery, compute, IMU, side and belly cameras, ultrasound |
| hips   | 4 hip housings   | 1.0 | motor housings at the body's corners |
| thighs | 4 thighs         | 1.0 | |
| calves | 4 calves         | 1.0 | |
| feet   | 4 foot spheres   | 0.5 | rubber, made to hit the ground |

Disturbance roles (paper Table IV, written for a biped) map to: hips -> hip
housings, feet -> feet, elbows -> the front calves (a quadruped's forelimb
"elbow" is its front knee), pelvis -> trunk, head -> head.
"""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, distribution
from pathlib import Path

import mujoco

from fallkit.api import ComponentSpec, JointSpec, RobotSpec, URDFError, robot_from_urdf

URDF_IN_DISTRIBUTION = "cmeel.prefix/share/example-robot-data/robots/go1_description/urdf/go1.urdf"

LEGS = ("FR", "FL", "RR", "RL")  # Unitree's order: front right, front left, rear right, rear left
# Policy order: hip, thigh, calf per leg, legs in Unitree's order.
JOINT_NAMES = [f"{leg}_{j}_joint" for leg in LEGS for j in ("hip", "thigh", "calf")]

ROTOR_INERTIA = 0.000111842  # kg·m², the URDF's *_rotor links about their spin axis
GEAR = {"hip": 6.0, "thigh": 6.0, "calf": 9.0}
TORQUE_LIMIT = {"hip": 23.7, "thigh": 23.7, "calf": 35.55}  # N·m, the URDF's efforts
KP, KD = 35.0, 0.5

# Standing: thighs 0.9 rad, knees -1.8 rad, trunk about 0.27 m high.
NOMINAL_POSE = {f"{leg}_{j}_joint": q for leg in LEGS for j, q in (("hip", 0.0), ("thigh", 0.9), ("calf", -1.8))}

COMPONENTS = {
    "head": (["head"], 4.0),
    "trunk": (["trunk"], 2.0),
    "hips": ([f"{leg}_hip" for leg in LEGS], 1.0),
    "thighs": ([f"{leg}_thigh" for leg in LEGS], 1.0),
    "calves": ([f"{leg}_calf" for leg in LEGS], 1.0),
    "feet": ([f"{leg}_foot" for leg in LEGS], 0.5),
}

DISTURBANCE_BODIES = {
    "hips": [f"{leg}_hip" for leg in LEGS],
    "feet": [f"{leg}_foot" for leg in LEGS],
    "elbows": ["FR_calf", "FL_calf"],
    "pelvis": ["trunk"],
    "head": ["head"],
}


def urdf_path() -> Path:
    """go1.urdf inside the installed example-robot-data distribution."""
    try:
        path = Path(distribution("example-robot-data").locate_file(URDF_IN_DISTRIBUTION))
    except PackageNotFoundError:
        raise URDFError("go1: example-robot-data is not installed (pip install example-robot-data)") from None
    if not path.is_file():
        raise URDFError(f"go1: {URDF_IN_DISTRIBUTION} is missing from example-robot-data at {path}")
    return path


def _add_head(spec: mujoco.MjSpec) -> None:
    """The face module in front of the URDF's trunk box (its mass is in the trunk's)."""
    head = spec.body("trunk").add_body(name="head", pos=[0.245, 0.0, 0.005])
    head.add_geom(name="head", type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.055, 0.065, 0.055], mass=0.0)


def go1() -> RobotSpec:
    """The Go1 (entry point `go1` of group `fallkit.robots`)."""
    kind = lambda joint: joint.split("_")[1]  # noqa: E731  FR_thigh_joint -> thigh
    return robot_from_urdf(
        "go1",
        urdf_path(),
        root_link="trunk",
        joints=[JointSpec(name=j, kp=KP, kd=KD, torque_limit=TORQUE_LIMIT[kind(j)]) for j in JOINT_NAMES],
        armature={j: ROTOR_INERTIA * GEAR[kind(j)] ** 2 for j in JOINT_NAMES},
        components={c: ComponentSpec(bodies=bodies, weight=w) for c, (bodies, w) in COMPONENTS.items()},
        nominal_pose=NOMINAL_POSE,
        disturbance_bodies=DISTURBANCE_BODIES,
        edit=_add_head,
        policy_hz=50.0,
        timestep=0.005,
    )
