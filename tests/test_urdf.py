"""URDF import: real example-robot-data robots (a biped, a quadruped), repairs, and clear errors."""

from __future__ import annotations

import os
import subprocess
import sys
import xml.etree.ElementTree as ET
from importlib.metadata import distribution
from pathlib import Path

import mujoco
import numpy as np
import pytest

from fallkit.api import (
    ComponentSpec,
    JointSpec,
    URDFError,
    URDFWarning,
    robot_from_urdf,
    urdf_to_mjcf,
)

ROBOTS = Path(distribution("example-robot-data").locate_file("cmeel.prefix/share/example-robot-data/robots"))
BOLT = ROBOTS / "bolt_description" / "robots" / "bolt.urdf"
GO1 = ROBOTS / "go1_description" / "urdf" / "go1.urdf"


def urdf_mass(path: Path) -> float:
    return sum(float(e.get("value")) for e in ET.parse(path).getroot().iterfind("link/inertial/mass"))


def bodies(model: mujoco.MjModel) -> list[str]:
    return [model.body(i).name for i in range(1, model.nbody)]


def settle(model: mujoco.MjModel, seconds: float) -> mujoco.MjData:
    """Drop the robot from 0.5 m with zero torque and let it come to rest."""
    m = model.__copy__()
    m.actuator_gainprm[:, 0] = 0
    m.actuator_biasprm[:, :3] = 0
    d = mujoco.MjData(m)
    d.qpos[2] = 0.5
    for _ in range(round(seconds / m.opt.timestep)):
        mujoco.mj_step(m, d)
    assert not d.warning[mujoco.mjtWarning.mjWARN_BADQACC].number
    return d


# ---- real robots ---------------------------------------------------------------------------


def test_bolt_biped(tmp_path):
    legs = [f"{s}_{j}" for s in ("FL", "FR") for j in ("HAA", "HFE", "KFE")]
    spec = robot_from_urdf(
        "bolt",
        BOLT,
        joints=[JointSpec(name=j, kp=3.0, kd=0.05, torque_limit=2.7) for j in legs],
        components={
            "base": ComponentSpec(bodies=["base_link"], weight=2.0),
            "legs": ComponentSpec(bodies=[f"{s}_{b}" for s in ("FL", "FR") for b in ("SHOULDER", "UPPER_LEG", "LOWER_LEG")], weight=1.0),
            "feet": ComponentSpec(bodies=["FL_FOOT", "FR_FOOT"], weight=0.5),
        },
        cache_dir=tmp_path,
    )
    m = spec.mj_model()
    assert spec.root_body == "base_link" and m.joint("root").type == mujoco.mjtJoint.mjJNT_FREE
    assert (m.nq, m.nu) == (7 + 6, 6)
    assert m.body_mass.sum() == pytest.approx(urdf_mass(BOLT), rel=1e-6)
    # the feet hang on fixed joints: kept as bodies because a component names them
    assert {"FL_FOOT", "FR_FOOT"} <= set(bodies(m))
    # STL collision meshes travel with the MJCF, by relative path: the same text on every machine
    text = spec.mjcf.read_text()
    assert (spec.mjcf.parent / "meshes" / "bolt_foot.stl").is_file()
    assert 'file="meshes/bolt_foot.stl"' in text and str(tmp_path) not in text and "package://" not in text
    assert m.ngeom > 0 and (m.geom_type == mujoco.mjtGeom.mjGEOM_MESH).sum() >= 8
    d = settle(m, 2.0)
    assert np.abs(d.qvel).max() < 0.5 and 0 < d.qpos[2] < 0.5


def test_go1_quadruped_with_its_bad_inertia_repaired(tmp_path):
    with pytest.warns(URDFWarning, match=r"go1\.urdf: link 'base': inertia is not physical"):
        mjcf = urdf_to_mjcf(GO1, cache_dir=tmp_path)
    assert "repaired: link 'base'" in mjcf.read_text()  # the MJCF says what was changed
    m = mujoco.MjModel.from_xml_path(str(mjcf))
    assert m.body(1).name == "base" and m.body_jntnum[1] == 0  # the root: RobotSpec adds its free joint
    assert m.njnt == 12 and all(m.jnt_type == mujoco.mjtJoint.mjJNT_HINGE)
    assert not m.jnt_actfrclimited.any()  # torque limits come from the JointSpecs only
    assert m.body_mass.sum() == pytest.approx(urdf_mass(GO1), rel=1e-6)
    # rotors, cameras and feet hang on fixed joints and are fused into their parents
    assert "FR_hip_rotor" not in bodies(m) and "FR_foot" not in bodies(m) and "trunk" not in bodies(m)
    # same URDF, same output: content-addressed and reused
    with pytest.warns(URDFWarning):
        assert urdf_to_mjcf(GO1, cache_dir=tmp_path) == mjcf

    # dropping the dummy base link removes the bad inertia; named links stay bodies
    kept = urdf_to_mjcf(GO1, cache_dir=tmp_path, root_link="trunk", keep_bodies=["FR_foot"])
    m2 = mujoco.MjModel.from_xml_path(str(kept))
    assert m2.body(1).name == "trunk" and "FR_foot" in bodies(m2) and "base" not in bodies(m2)


# ---- repairs and errors on small URDFs -----------------------------------------------------------


def write_urdf(folder: Path, collision: str = '<geometry><box size="0.2 0.1 0.1"/></geometry>',
               inertia: str = 'ixx="0.01" iyy="0.01" izz="0.01" ixy="0" ixz="0" iyz="0"',
               origin: str = "") -> Path:  # fmt: skip
    path = folder / "robot.urdf"
    path.write_text(f"""<?xml version="1.0"?>
<robot name="two_links">
  <link name="body">
    <inertial>{origin}<mass value="2.0"/><inertia {inertia}/></inertial>
    <collision>{collision}</collision>
  </link>
  <link name="arm">
    <inertial><mass value="0.5"/><inertia ixx="0.001" iyy="0.001" izz="0.001" ixy="0" ixz="0" iyz="0"/></inertial>
    <collision><geometry><cylinder radius="0.02" length="0.3"/></geometry></collision>
  </link>
  <link name="tip"/>
  <joint name="shoulder" type="revolute">
    <parent link="body"/><child link="arm"/><axis xyz="0 1 0"/>
    <limit lower="-1.5" upper="1.5" effort="5" velocity="10"/>
  </joint>
  <joint name="tip_fixed" type="fixed"><parent link="arm"/><child link="tip"/></joint>
</robot>
""")
    return path


def test_missing_file(tmp_path):
    with pytest.raises(URDFError, match=r"nothere\.urdf: URDF file not found"):
        urdf_to_mjcf(tmp_path / "nothere.urdf", cache_dir=tmp_path)


def test_malformed_xml_names_the_line(tmp_path):
    bad = tmp_path / "bad.urdf"
    bad.write_text('<robot name="x">\n  <link name="a">\n</robot>\n')
    with pytest.raises(URDFError, match=r"bad\.urdf:3:\d+: malformed XML: mismatched tag"):
        urdf_to_mjcf(bad, cache_dir=tmp_path)


def test_not_a_urdf(tmp_path):
    path = tmp_path / "model.xml"
    path.write_text("<mujoco/>")
    with pytest.raises(URDFError, match=r"model\.xml: not a URDF: the root element is <mujoco>"):
        urdf_to_mjcf(path, cache_dir=tmp_path)


def test_missing_mesh_names_link_and_file(tmp_path):
    path = write_urdf(tmp_path, collision='<geometry><mesh filename="meshes/shell.stl"/></geometry>')
    with pytest.raises(URDFError, match=r"robot\.urdf: link 'body': collision mesh 'meshes/shell\.stl': file not found"):
        urdf_to_mjcf(path, cache_dir=tmp_path)
    path = write_urdf(tmp_path, collision='<geometry><mesh filename="package://nopkg/shell.stl"/></geometry>')
    with pytest.raises(URDFError, match=r"link 'body'.*package 'nopkg' not found.*package_dirs"):
        urdf_to_mjcf(path, cache_dir=tmp_path)


def test_package_paths_resolve_through_package_dirs(tmp_path):
    pkg = tmp_path / "elsewhere" / "my_robot"
    (pkg / "meshes").mkdir(parents=True)
    (pkg / "meshes" / "foot.stl").write_bytes((BOLT.parent.parent / "meshes" / "stl" / "bolt_foot.stl").read_bytes())
    path = write_urdf(tmp_path, collision='<geometry><mesh filename="package://my_robot/meshes/foot.stl"/></geometry>')
    mjcf = urdf_to_mjcf(path, cache_dir=tmp_path / "cache", package_dirs={"my_robot": pkg})
    m = mujoco.MjModel.from_xml_path(str(mjcf))
    assert m.nmesh == 1 and (mjcf.parent / "meshes" / "foot.stl").is_file()


def test_unreadable_mesh_becomes_the_equivalent_inertia_box(tmp_path):
    # Inertia of a 0.4 x 0.2 x 0.1 m box of 2 kg, its long axis turned 0.3 rad about z.
    a, b, c, mass = 0.4, 0.2, 0.1, 2.0
    diag = mass / 12 * np.array([b**2 + c**2, a**2 + c**2, a**2 + b**2])
    rot = np.array([[np.cos(0.3), -np.sin(0.3), 0], [np.sin(0.3), np.cos(0.3), 0], [0, 0, 1]])
    inertia = rot @ np.diag(diag) @ rot.T
    (tmp_path / "shell.dae").write_text("<COLLADA/>")  # MuJoCo reads no Collada
    path = write_urdf(
        tmp_path,
        collision='<geometry><mesh filename="shell.dae"/></geometry>',
        inertia=" ".join(f'{k}="{float(inertia[i, j])!r}"' for k, (i, j) in
                         dict(ixx=(0, 0), iyy=(1, 1), izz=(2, 2), ixy=(0, 1), ixz=(0, 2), iyz=(1, 2)).items()),
        origin='<origin xyz="0.05 0 0.02"/>',
    )  # fmt: skip
    with pytest.warns(URDFWarning, match=r"link 'body': MuJoCo cannot read collision meshes \['shell\.dae'\]; replaced by a"):
        mjcf = urdf_to_mjcf(path, cache_dir=tmp_path)
    m = mujoco.MjModel.from_xml_path(str(mjcf))
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    (box,) = np.flatnonzero((m.geom_bodyid == m.body("body").id) & (m.geom_type == mujoco.mjtGeom.mjGEOM_BOX))
    order = np.argsort(m.geom_size[box])[::-1]
    assert m.geom_size[box][order] == pytest.approx([a / 2, b / 2, c / 2], rel=1e-4)
    long_axis = d.geom_xmat[box].reshape(3, 3)[:, order[0]]
    assert abs(long_axis @ [np.cos(0.3), np.sin(0.3), 0]) == pytest.approx(1.0, abs=1e-6)
    assert d.geom_xpos[box] == pytest.approx([0.05, 0, 0.02], abs=1e-9)


def test_triangle_violating_inertia_is_balanced(tmp_path):
    path = write_urdf(tmp_path, inertia='ixx="0.001" iyy="0.001" izz="0.01" ixy="0" ixz="0" iyz="0"')
    with pytest.warns(URDFWarning, match=r"link 'body': inertia is not physical .* A \+ B >= C"):
        mjcf = urdf_to_mjcf(path, cache_dir=tmp_path)
    m = mujoco.MjModel.from_xml_path(str(mjcf))
    assert m.body_inertia[m.body("body").id] == pytest.approx([0.004] * 3)  # same trace, all axes equal


def test_joints_named_in_the_spec_must_be_revolute_joints_of_the_urdf(tmp_path):
    path = write_urdf(tmp_path)
    components = {"all": ComponentSpec(bodies=["body", "arm"], weight=1.0)}
    spec = robot_from_urdf("two", path, joints=[JointSpec(name="shoulder", kp=5, kd=0.1, torque_limit=5)],
                           components=components, cache_dir=tmp_path)  # fmt: skip
    assert spec.mj_model().nu == 1 and spec.joint_limits.tolist() == [[-1.5, 1.5]]
    with pytest.raises(URDFError, match=r"robot\.urdf: joints: no joint 'elbow' in the URDF; its revolute joints are \['shoulder'\]"):
        robot_from_urdf("two", path, joints=[JointSpec(name="elbow", kp=5, kd=0.1, torque_limit=5)], cache_dir=tmp_path)
    with pytest.raises(URDFError, match=r"joint 'tip_fixed' is fixed; only revolute and continuous"):
        robot_from_urdf("two", path, joints=[JointSpec(name="tip_fixed", kp=5, kd=0.1, torque_limit=5)], cache_dir=tmp_path)
    with pytest.raises(URDFError, match=r"robot\.urdf: components\.hand: no link .hand. in the URDF \(links: arm, body, tip\)"):
        robot_from_urdf("two", path, joints=[JointSpec(name="shoulder", kp=5, kd=0.1, torque_limit=5)],
                        components={"hand": ComponentSpec(bodies=["hand"], weight=1.0)}, cache_dir=tmp_path)  # fmt: skip
    with pytest.raises(URDFError, match=r"root_link 'arm': joint 'shoulder' above it is revolute"):
        urdf_to_mjcf(path, root_link="arm", cache_dir=tmp_path)


def test_a_revolute_joint_without_limits_warns_and_spans_pi(tmp_path):
    path = write_urdf(tmp_path)
    path.write_text(path.read_text().replace('<limit lower="-1.5" upper="1.5" effort="5" velocity="10"/>', ""))
    with pytest.warns(URDFWarning, match=r"robot\.urdf: joint 'shoulder' is revolute without <limit lower=… upper=…>: "
                                         r"it is simulated unlimited"):  # fmt: skip
        spec = robot_from_urdf("two", path, joints=[JointSpec(name="shoulder", kp=5, kd=0.1, torque_limit=5)],
                               components={"all": ComponentSpec(bodies=["body", "arm"], weight=1.0)},
                               cache_dir=tmp_path)  # fmt: skip
    assert spec.joint_limits[0].tolist() == pytest.approx([-np.pi, np.pi])


def test_mode_list_shows_the_plugins_and_their_distributions(tmp_path):
    # The example plugin's reward weight and sampler role must also pass config validation.
    args = ["mode=list", "+reward.root_spin=0.5", "env.samplers.initial_state=standing_push"]
    r = subprocess.run([sys.executable, "-m", "fallkit", *args], cwd=tmp_path, capture_output=True, text=True,
                       env={**os.environ, "PYTHONUNBUFFERED": "1"}, timeout=120)  # fmt: skip
    assert r.returncode == 0, r.stderr
    listed = {line.split()[0]: line for line in r.stdout.splitlines() if line.startswith("  ")}
    install = "install the plugins: pip install -e plugins/fallkit-go1 -e plugins/fallkit-example"
    for name, where in [
        ("go1", "fallkit-go1 (fallkit_go1.robot:go1)"),
        ("root_spin", "fallkit-example (fallkit_example.rewards:root_spin)"),
        ("standing_push", "fallkit-example (fallkit_example.samplers:standing_push)"),
    ]:
        assert name in listed, f"{name} is not listed; {install}\n{r.stdout}"
        assert where in listed[name] and "ERROR" not in listed[name]
