"""The Go1 plugin: found through its entry point, the model it builds, standing and falling in MuJoCo.

Uses only fallkit's public API (`fallkit.api`, `RobotSpec.mj_model()`) and MuJoCo itself,
as a third-party plugin's tests would.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from importlib.metadata import entry_points

import mujoco
import numpy as np
import pytest

from fallkit.api import RobotSpec, get_robot, list_robots
from fallkit_go1.robot import JOINT_NAMES, urdf_path


@pytest.fixture(scope="module")
def go1() -> RobotSpec:
    return get_robot("go1")


def test_registered_by_this_distribution(go1):
    assert "go1" in list_robots()
    (ep,) = [ep for ep in entry_points(group="fallkit.robots") if ep.name == "go1"]
    assert ep.dist.name == "fallkit-go1" and ep.value == "fallkit_go1.robot:go1"
    assert isinstance(go1, RobotSpec) and go1.name == "go1"


def test_model_matches_the_urdf(go1):
    m = go1.mj_model()
    # every URDF link's mass is kept: rotors, sensors and the dummy base are fused or dropped, not lost
    urdf_mass = sum(float(e.get("value")) for e in ET.parse(urdf_path()).getroot().iterfind("link/inertial/mass"))
    assert m.body_mass.sum() == pytest.approx(urdf_mass - 1e-6, rel=1e-6)  # minus the 1 mg base link
    assert m.body_mass.sum() == pytest.approx(13.1, abs=0.05)
    assert (m.nq, m.nv, m.nu) == (7 + 12, 6 + 12, 12)
    assert go1.joint_names == JOINT_NAMES
    assert [m.actuator(i).name for i in range(m.nu)] == JOINT_NAMES
    assert m.actuator_forcerange[:, 1].tolist() == [23.7, 23.7, 35.55] * 4
    assert np.all(m.dof_armature[6:] > 0)
    assert go1.policy_hz == 50 and go1.substeps == 4


def test_components_cover_the_robot(go1):
    m = go1.mj_model()
    weights = {c: comp.weight for c, comp in go1.components.items()}
    assert weights == {"head": 4.0, "trunk": 2.0, "hips": 1.0, "thighs": 1.0, "calves": 1.0, "feet": 0.5}
    bodies = [b for comp in go1.components.values() for b in comp.bodies]
    assert sorted(bodies) == sorted(m.body(i).name for i in range(1, m.nbody))
    for role, names in go1.disturbance_bodies.items():
        assert role in {"hips", "feet", "elbows", "pelvis", "head"}
        assert all(m.body(n).id > 0 for n in names)
    # the head sits in front of the trunk
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    assert d.xpos[m.body("head").id, 0] > d.xpos[m.body("trunk").id, 0] + 0.2


def _worlds(spec: RobotSpec, gain_scale: float = 1.0) -> tuple[mujoco.MjModel, mujoco.MjData]:
    m = spec.mj_model().__copy__()
    m.actuator_gainprm[:, 0] *= gain_scale
    m.actuator_biasprm[:, 1:3] *= gain_scale
    return m, mujoco.MjData(m)


def _contact(m: mujoco.MjModel, d: mujoco.MjData, component: str, spec: RobotSpec) -> float:
    """Net contact force [N] on a component, from the spec's contact sensors."""
    total = np.zeros(3)
    for body in spec.components[component].bodies:
        total += d.sensor(f"contact_{body}").data
    return float(np.linalg.norm(total))


def test_stands_on_its_feet(go1):
    m, d = _worlds(go1)
    d.qpos[2] = 0.30
    d.qpos[3:7] = [1, 0, 0, 0]
    d.qpos[7:] = go1.nominal_q()
    d.ctrl[:] = go1.nominal_q()
    for _ in range(round(3.0 / m.opt.timestep)):
        mujoco.mj_step(m, d)
    assert 0.22 < d.qpos[2] < 0.30  # standing, knees sagging a little under kp = 35
    up = d.xmat[m.body("trunk").id].reshape(3, 3)[:, 2]
    assert up[2] > np.cos(0.1)  # level within 0.1 rad
    assert np.abs(d.qvel).max() < 1e-2  # at rest
    weight = m.body_mass.sum() * 9.81
    assert _contact(m, d, "feet", go1) == pytest.approx(weight, rel=0.02)
    assert all(_contact(m, d, c, go1) == 0 for c in go1.components if c != "feet")


@pytest.mark.parametrize("strategy,scale", [("zero_torque", 0.0), ("freeze", 10.0)])
def test_falls_are_stable(go1, strategy, scale):
    """Tipped over with a kick, limp or stiff: no instability, comes to rest with its weight on the floor."""
    m, d = _worlds(go1, scale)
    rng = np.random.default_rng(0)
    for trial in range(4):
        mujoco.mj_resetData(m, d)
        roll, pitch = rng.uniform(-0.5, 0.5, 2) + [np.pi / 2 * (trial % 2), 0.0]  # half of them on their side
        d.qpos[2] = 0.35
        mujoco.mju_euler2Quat(d.qpos[3:7], [roll, pitch, 0.0], "XYZ")
        d.qpos[7:] = go1.nominal_q()
        d.ctrl[:] = go1.nominal_q()
        d.qvel[:3] = rng.uniform(-2, 2, 3)
        for _ in range(round(3.0 / m.opt.timestep)):
            mujoco.mj_step(m, d)
        assert not d.warning[mujoco.mjtWarning.mjWARN_BADQACC].number, f"{strategy} trial {trial}: unstable"
        assert np.isfinite(d.qpos).all() and np.abs(d.qvel).max() < 0.5, f"{strategy} trial {trial}: not at rest"
        support = sum(_contact(m, d, c, go1) for c in go1.components)
        assert support >= 0.9 * m.body_mass.sum() * 9.81  # lying on the floor, not hovering or sunk
