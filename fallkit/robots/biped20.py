"""biped20: a 20-DoF biped standing in for the paper's robot (Sec. V-A "Robot").

16.2 kg, 0.84 m; 5-DoF legs with Unitree-A1-class actuators (33.5 N·m), arms
and neck with Dynamixel-XH540-class servos (7 N·m). Joint axes and sign
conventions are documented in the README ("Authoring a pose").

Components and sensitivity weights follow the paper: pelvis and legs 1.0,
elbows 2.0, shoulders 3.0, head 4.0. The paper's critical-component experiment
(Sec. V-E, Table VI) splits the rear battery pack off the pelvis as its own
component: `biped20_battery` weights the battery 5.0 and every other component
1.0, and its baseline `biped20_battery_baseline` weights every component 1.0.
"""

from __future__ import annotations

from pathlib import Path

from fallkit.robots.spec import ComponentSpec, JointSpec, RobotSpec, make_robot_spec

MJCF = Path(__file__).parent / "assets" / "biped20.xml"

# (kp [N·m/rad], kd [N·m·s/rad], torque limit [N·m]). Leg gains hold the robot
# standing at the nominal pose (kp 40 was measured to tip over backward: the
# stance's gravity stiffness about the ankles is about 67 N·m/rad).
_A1_HIP_YAW = (60.0, 1.5, 33.5)
_A1 = (100.0, 2.5, 33.5)
_XH540 = (10.0, 0.3, 7.0)

_GAINS: dict[str, tuple[float, float, float]] = {
    "neck_yaw": _XH540,
    "neck_pitch": _XH540,
    **{f"{s}_{j}": _XH540 for s in ("left", "right") for j in ("shoulder_pitch", "shoulder_roll", "shoulder_yaw", "elbow")},
    **{
        f"{s}_{j}": g
        for s in ("left", "right")
        for j, g in (
            ("hip_yaw", _A1_HIP_YAW),
            ("hip_roll", _A1),
            ("hip_pitch", _A1),
            ("knee", _A1),
            ("ankle_pitch", _A1),
        )
    },
}

JOINT_NAMES = [
    "neck_yaw", "neck_pitch",
    "left_shoulder_pitch", "left_shoulder_roll", "left_shoulder_yaw", "left_elbow",
    "right_shoulder_pitch", "right_shoulder_roll", "right_shoulder_yaw", "right_elbow",
    "left_hip_yaw", "left_hip_roll", "left_hip_pitch", "left_knee", "left_ankle_pitch",
    "right_hip_yaw", "right_hip_roll", "right_hip_pitch", "right_knee", "right_ankle_pitch",
]  # fmt: skip

NOMINAL_POSE = {
    "left_hip_pitch": -0.25, "left_knee": 0.5, "left_ankle_pitch": -0.25,
    "right_hip_pitch": -0.25, "right_knee": 0.5, "right_ankle_pitch": -0.25,
    "left_elbow": -0.3, "right_elbow": -0.3,
}  # fmt: skip

_LEGS = [f"{s}_{b}" for s in ("left", "right") for b in ("hip_yaw_link", "hip_roll_link", "thigh", "shin", "foot")]
_SHOULDERS = [f"{s}_{b}" for s in ("left", "right") for b in ("shoulder_pitch_link", "shoulder_roll_link", "upper_arm")]


def _components(battery_split: bool, battery_weight: float | None = None) -> dict[str, ComponentSpec]:
    """biped20's components; with `battery_weight` the battery is its own component at that
    weight and every other component weighs 1.0 (the paper's battery experiment)."""
    comps = {
        "pelvis": ComponentSpec(bodies=["pelvis"] if battery_split else ["pelvis", "battery"], weight=1.0),
        "legs": ComponentSpec(bodies=_LEGS, weight=1.0),
        "elbows": ComponentSpec(bodies=["left_forearm", "right_forearm"], weight=2.0),
        "shoulders": ComponentSpec(bodies=_SHOULDERS, weight=3.0),
        "head": ComponentSpec(bodies=["neck_yaw_link", "head"], weight=4.0),
    }
    if battery_weight is not None:
        comps = {k: c.model_copy(update={"weight": 1.0}) for k, c in comps.items()}
        comps["battery"] = ComponentSpec(bodies=["battery"], weight=battery_weight)
    return comps


def _spec(name: str, battery_weight: float | None = None) -> RobotSpec:
    return make_robot_spec(
        name,
        mjcf=MJCF,
        root_body="pelvis",
        joints=[JointSpec(name=j, kp=_GAINS[j][0], kd=_GAINS[j][1], torque_limit=_GAINS[j][2]) for j in JOINT_NAMES],
        components=_components(battery_weight is not None, battery_weight),
        nominal_pose=NOMINAL_POSE,
        disturbance_bodies={
            "hips": ["left_hip_roll_link", "right_hip_roll_link"],
            "feet": ["left_foot", "right_foot"],
            "elbows": ["left_forearm", "right_forearm"],
            "pelvis": ["pelvis"],
            "head": ["head"],
        },
        policy_hz=50.0,
        timestep=0.005,
    )


def biped20() -> RobotSpec:
    """The built-in biped (entry point `biped20`)."""
    return _spec("biped20")


def biped20_battery() -> RobotSpec:
    """The paper's battery experiment: the rear battery pack its own component at weight 5.0, every
    other component 1.0 (entry point `biped20_battery`)."""
    return _spec("biped20_battery", battery_weight=5.0)


def biped20_battery_baseline() -> RobotSpec:
    """Its baseline: the same components, every weight 1.0 (entry point `biped20_battery_baseline`)."""
    return _spec("biped20_battery_baseline", battery_weight=1.0)
