from importlib.resources import files

from fallkit.api import ComponentSpec, JointSpec, RobotSpec, get_robot, make_robot_spec

NOT_CALLABLE = 42


def biped20_again() -> RobotSpec:
    return get_robot("biped20")


def not_a_spec() -> dict:
    return {"name": "not a spec"}


def tiny_biped() -> RobotSpec:
    """A valid third-party robot: biped20's body with only the neck actuated."""
    return make_robot_spec(
        "tiny_biped",
        mjcf=files("fallkit.robots") / "assets" / "biped20.xml",
        root_body="pelvis",
        joints=[JointSpec(name=j, kp=10.0, kd=0.3, torque_limit=7.0) for j in ("neck_yaw", "neck_pitch")],
        components={"trunk": ComponentSpec(bodies=["pelvis", "battery"], weight=1.0),
                    "head": ComponentSpec(bodies=["neck_yaw_link", "head"], weight=4.0)},
        nominal_pose={},
    )
