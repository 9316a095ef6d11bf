"""biped20 matches the paper's robot; RobotSpec validation names robot and field."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
import torch

from fallkit.api import ComponentSpec, JointSpec, RobotSpecError, get_robot, make_robot_spec
from fallkit.poses.checker import PoseChecker

JOINTS = [
    "neck_yaw", "neck_pitch",
    "left_shoulder_pitch", "left_shoulder_roll", "left_shoulder_yaw", "left_elbow",
    "right_shoulder_pitch", "right_shoulder_roll", "right_shoulder_yaw", "right_elbow",
    "left_hip_yaw", "left_hip_roll", "left_hip_pitch", "left_knee", "left_ankle_pitch",
    "right_hip_yaw", "right_hip_roll", "right_hip_pitch", "right_knee", "right_ankle_pitch",
]  # fmt: skip


def test_biped20_matches_the_paper(biped):
    m = biped.mj_model()
    assert biped.joint_names == JOINTS
    assert m.nu == 20 and m.nq == 7 + 20
    assert m.body_mass.sum() == pytest.approx(16.2, rel=0.03)
    assert biped.policy_hz == 50 and biped.substeps == 4
    weights = {c: comp.weight for c, comp in biped.components.items()}
    assert weights == {"pelvis": 1.0, "legs": 1.0, "elbows": 2.0, "shoulders": 3.0, "head": 4.0}
    # every body but the world belongs to exactly one component
    bodies = [b for comp in biped.components.values() for b in comp.bodies]
    assert sorted(bodies) == sorted(m.body(i).name for i in range(1, m.nbody))


def test_standing_height(biped):
    checker = PoseChecker(biped)
    lay = checker.layout
    q = lay.qpos(torch.zeros(1, 3, dtype=torch.float64), torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64),
                 torch.tensor(biped.nominal_q())[None])  # fmt: skip
    q, colliding = checker.place_on_ground(q, 0.0)
    assert not colliding.item()
    m = biped.mj_model()
    d = mujoco.MjData(m)
    d.qpos[:] = q[0].numpy()
    mujoco.mj_forward(m, d)
    head = m.body("head").id
    def top_of(g: int) -> float:  # highest point of the geom's bounding box
        rz = d.geom_xmat[g].reshape(3, 3)[2]
        return d.geom_xpos[g, 2] + rz @ m.geom_aabb[g, :3] + np.abs(rz) @ m.geom_aabb[g, 3:]

    top = max(top_of(g) for g in range(m.ngeom) if m.geom_bodyid[g] == head)
    assert top == pytest.approx(0.84, rel=0.03)


def test_every_link_collides(biped):
    m = biped.mj_model()
    for b in range(1, m.nbody):
        geoms = [g for g in range(m.ngeom) if m.geom_bodyid[g] == b and (m.geom_contype[g] or m.geom_conaffinity[g])]
        assert geoms, f"body {m.body(b).name} has no collision geometry"


def test_battery_variants_are_the_papers(biped):
    """Sec. V-E / Table VI: battery 5.0 and every other component 1.0, against all weights 1.0."""
    battery, baseline = get_robot("biped20_battery"), get_robot("biped20_battery_baseline")
    assert {k: c.weight for k, c in battery.components.items()} == {
        "pelvis": 1.0, "legs": 1.0, "elbows": 1.0, "shoulders": 1.0, "head": 1.0, "battery": 5.0}
    assert {c.weight for c in baseline.components.values()} == {1.0} and "battery" in baseline.components
    assert battery.components["battery"].bodies == ["battery"]
    assert "battery" not in battery.components["pelvis"].bodies
    assert battery.mj_model().body_mass.sum() == pytest.approx(biped.mj_model().body_mass.sum())
    assert battery.model_hash() == baseline.model_hash() == biped.model_hash()  # one body, one dataset


def test_sensitivity_override(biped):
    heavier = biped.with_sensitivity({"head": 6.0})
    assert heavier.components["head"].weight == 6.0 and biped.components["head"].weight == 4.0
    with pytest.raises(RobotSpecError, match="unknown components \\['tail'\\]"):
        biped.with_sensitivity({"tail": 1.0})


def _fields(biped, **changes):
    fields = dict(mjcf=biped.mjcf, root_body="pelvis", joints=list(biped.joints), components=dict(biped.components),
                  nominal_pose=dict(biped.nominal_pose))  # fmt: skip
    fields.update(changes)
    return fields


def test_validation_errors_name_robot_and_field(biped):
    with pytest.raises(RobotSpecError, match=r"robot 'r1': joints\.0\.kp: Input should be greater than 0"):
        make_robot_spec("r1", **_fields(biped, joints=[{"name": "neck_yaw", "kp": -1, "kd": 0, "torque_limit": 1}]))
    with pytest.raises(RobotSpecError, match=r"robot 'r2': mjcf: .*MJCF file not found"):
        make_robot_spec("r2", **_fields(biped, mjcf="/no/such/robot.xml"))
    with pytest.raises(RobotSpecError, match=r"robot 'r3': .*nominal_pose: unknown joints \['tail'\]"):
        make_robot_spec("r3", **_fields(biped, nominal_pose={"tail": 0.1}))
    spec = make_robot_spec("r4", **_fields(biped, nominal_pose={"left_knee": 3.0}))
    with pytest.raises(RobotSpecError, match=r"robot 'r4': nominal_pose.left_knee: 3.000 rad is outside"):
        spec.mj_model()
    spec = make_robot_spec("r5", **_fields(biped, components={"x": ComponentSpec(bodies=["wing"], weight=1.0)}))
    with pytest.raises(RobotSpecError, match=r"robot 'r5': components.x: no body 'wing'"):
        spec.mj_model()
    spec = make_robot_spec("r6", **_fields(biped, joints=[JointSpec(name="tail", kp=1, kd=0, torque_limit=1)], nominal_pose={}))
    with pytest.raises(RobotSpecError, match=r"robot 'r6': joints: no joint 'tail'"):
        spec.mj_model()


def test_substeps_must_divide(biped):
    with pytest.raises(RobotSpecError, match="policy_hz"):
        make_robot_spec("r7", **_fields(biped), policy_hz=30.0)
