"""The fall detector (issue 17, part 3): it watches a standing robot and says when a fall has begun, early
enough for the fall policy to act. Judged in the real simulator (one MjData, MuJoCo's PD servos), from
the same exported dict a robot loads."""

from __future__ import annotations

import json
import math

import mujoco
import numpy as np
import pytest
from helpers import TINY, composed_config, fallkit_cli

from fallkit.config import ConfigError
from fallkit.config.detector import DetectorConfig
from fallkit.deploy import DeployError, FallDetector, RobotState
from fallkit.deploy.detector import DetectorSettings, convex_hull, first_trigger, signed_distance
from fallkit.deploy.fall_detection import check_live, estimate, push_trials, standing_qpos
from fallkit.robots import get_robot
from fallkit.robots.kinematics import detector_export, exported_detector
from fallkit.sim.base import Layout


def detector(robot: str = "biped20", **settings) -> tuple:
    spec = get_robot(robot)
    cfg = DetectorConfig(**settings)
    return spec, cfg, FallDetector(detector_export(spec, cfg))


@pytest.mark.parametrize("robot", ["biped20", "go1"])
def test_the_numpy_kinematics_equal_mujoco(robot):
    """COM and COM velocity from the exported model (joint encoders, IMU, base velocity) equal MuJoCo's in
    random states; standing, the COM height above the lowest sole point is the COM's height above the floor."""
    spec, _, det = detector(robot)
    m, lay = spec.mj_model(), Layout(spec)
    d, root = mujoco.MjData(m), m.body(spec.root_body).id
    rng = np.random.default_rng(0)
    for _ in range(5):
        d.qpos[:] = m.qpos0
        d.qpos[lay.joint_qpos.numpy()] = rng.uniform(spec.joint_limits[:, 0], spec.joint_limits[:, 1])
        quat = rng.normal(size=4)
        d.qpos[lay.root_qpos + 3 : lay.root_qpos + 7] = quat / np.linalg.norm(quat)
        d.qvel[:] = rng.normal(size=m.nv)
        mujoco.mj_forward(m, d)
        mujoco.mj_subtreeVel(m, d)
        s = det.measure(estimate(d, lay))
        np.testing.assert_allclose(s.com, d.subtree_com[root] - d.xpos[root], atol=1e-12)
        np.testing.assert_allclose(s.com_velocity, d.subtree_linvel[root], atol=1e-12)
    d.qpos[:], d.qvel[:] = standing_qpos(spec), 0.0
    mujoco.mj_forward(m, d)
    s = det.measure(estimate(d, lay))
    assert s.com_height == pytest.approx(d.subtree_com[root][2], abs=1e-9)
    assert s.support_points == (8 if robot == "biped20" else 4)  # two box soles' bottoms; four foot spheres
    assert s.tilt == pytest.approx(0.0, abs=1e-12) and s.capture_distance < -0.03  # upright, well inside


@pytest.mark.parametrize("robot", ["biped20", "go1"])
def test_a_robot_standing_unpushed_never_triggers(robot):
    spec, cfg, det = detector(robot, pushes={"count": 1, "max_impulse": 0.0, "settle": 0.0, "after": 0.0})
    record = push_trials(spec, det, cfg.pushes)
    assert math.isnan(record.contact_time[0]) and record.live_trigger[0] == -1 and det.steps == 100  # 2 s at 50 Hz
    assert np.nanmax(record.capture[0]) < cfg.capture_margin - 0.02 and np.nanmax(record.tilt[0]) < cfg.max_tilt / 3


def test_large_pushes_trigger_before_the_first_non_foot_contact():
    """Pushes of 8 to 56 N·s from four directions: every one a fall, every one detected with time to spare."""
    spec, cfg, det = detector(pushes={"count": 4, "max_impulse": 64.0, "settle": 0.2, "after": 0.0, "seed": 1})
    record = push_trials(spec, det, cfg.pushes)
    assert (record.contact_time <= cfg.pushes.horizon).all()
    assert (record.live_trigger >= 0).all()
    lead = record.contact_time - record.time[record.live_trigger]
    assert (lead >= 0.15).all(), lead
    assert (record.time[record.live_trigger] >= 0).all()  # nothing before the push
    check_live(record, det.settings)  # the sweep's rule triggers where the live detector did


def test_confirm_steps_delay_the_trigger_as_the_sweep_says():
    spec, cfg, det = detector(confirm_steps=3, pushes={"count": 2, "max_impulse": 24.0, "settle": 0.1, "after": 0.0})
    record = push_trials(spec, det, cfg.pushes)
    check_live(record, det.settings)
    once = [first_trigger(record.capture[i], record.tilt[i], cfg.capture_margin, cfg.max_tilt) for i in range(2)]
    assert [int(k) for k in record.live_trigger] == [k + 2 for k in once]  # the signals only grow during a fall


def test_first_trigger_is_the_update_rule_over_a_record():
    capture, tilt = np.array([0.0, 0.1, 0.0, 0.1, 0.1, 0.0]), np.zeros(6)
    assert first_trigger(capture, tilt, 0.05, 1.0) == 1
    assert first_trigger(capture, tilt, 0.05, 1.0, confirm_steps=2) == 4
    assert first_trigger(capture, tilt, 0.2, 1.0) == -1
    assert first_trigger(capture, np.array([0, 0, 2.0, 0, 0, 0]), 0.2, 1.0) == 2  # the tilt backstop


def test_support_polygon_geometry():
    square = np.array([[0, 0], [1, 0], [1, 1], [0, 1], [0.5, 0.5], [0.5, 0.0]], dtype=float)  # inner, collinear
    hull = convex_hull(square)
    (ax, ay), (bx, by) = hull[1] - hull[0], hull[2] - hull[1]
    assert len(hull) == 4 and ax * by - ay * bx > 0  # counter-clockwise
    assert signed_distance(np.array([0.5, 0.5]), hull) == pytest.approx(-0.5)
    assert signed_distance(np.array([0.9, 0.5]), hull) == pytest.approx(-0.1)
    assert signed_distance(np.array([1.3, 0.5]), hull) == pytest.approx(0.3)
    assert signed_distance(np.array([2.0, 2.0]), hull) == pytest.approx(math.sqrt(2))  # nearest: the corner
    segment = convex_hull(np.array([[0.0, 0.0], [1.0, 0.0], [0.5, 0.0]]))
    assert len(segment) == 2 and signed_distance(np.array([0.5, 0.2]), segment) == pytest.approx(0.2)


def test_the_detector_of_an_export_equals_the_configured_one(tmp_path):
    from fallkit.rl.export import run_export
    from fallkit.rl.trainer import Trainer

    chosen = ("detector.capture_margin=0.07", "detector.confirm_steps=2", "detector.max_tilt=0.5",
              "detector.feet=[left_foot,right_foot]")  # fmt: skip
    Trainer(composed_config(*TINY, "train.iterations=1"), tmp_path / "run").run()
    out = tmp_path / "export"
    out.mkdir()
    run_export(composed_config(*TINY, *chosen, f"checkpoint={tmp_path / 'run'}", "mode=export"), out)
    loaded = FallDetector.load(out)
    spec, configured = get_robot("biped20"), composed_config(*chosen).detector
    assert loaded.meta == detector_export(spec, configured)
    assert loaded.settings == DetectorSettings(capture_margin=0.07, max_tilt=0.5, confirm_steps=2, contact_height=0.01)
    # the same pushes, watched by the loaded detector and by one built from the config, trigger alike
    pushes = configured.pushes.model_copy(update={"count": 3, "max_impulse": 30.0, "after": 0.0})
    a, b = push_trials(spec, loaded, pushes), push_trials(spec, FallDetector(detector_export(spec, configured)), pushes)
    np.testing.assert_array_equal(a.live_trigger, b.live_trigger)
    np.testing.assert_array_equal(a.capture, b.capture)


def test_bad_detector_settings_are_one_line_errors(tmp_path):
    with pytest.raises(ConfigError, match=r"^detector.max_tilt: Input should be greater than 0 \(got -1\)$"):
        composed_config("detector.max_tilt=-1")
    with pytest.raises(ConfigError, match=r"^detector.feet: name each foot body once, at least one"):
        composed_config("detector.feet=[left_foot,left_foot]")
    with pytest.raises(ConfigError, match=r"^detector.pushes.sweep: need low < high"):
        composed_config("detector.pushes.sweep=[0.2,0.1]")
    with pytest.raises(ConfigError, match=r"^detector.feet: robot 'biped20' has no body 'left_fot'; did you mean 'left_foot'\?$"):
        detector(feet=["left_fot"])
    r = fallkit_cli("mode=detect", "detector.feet=[left_foot,right_fot]", f"hydra.run.dir={tmp_path}", cwd=tmp_path)
    assert r.returncode == 2
    assert r.stderr.strip().splitlines() == ["fallkit: error: detector.feet: robot 'biped20' has no body 'right_fot'; "
                                             "did you mean 'right_foot'?"]  # fmt: skip


def test_a_bad_export_is_one_deploy_error(tmp_path):
    spec, cfg, _ = detector()
    meta = detector_export(spec, cfg)
    with pytest.raises(DeployError, match=r"policy.json not found"):
        FallDetector.load(tmp_path)
    (tmp_path / "policy.json").write_text(json.dumps({"robot": "biped20"}))
    with pytest.raises(DeployError, match=r"policy.json: has no fall_detector; export the policy with this fallkit"):
        FallDetector.load(tmp_path)
    footless = spec.model_copy(update={"disturbance_bodies": {}})  # a robot that names no feet still exports
    assert exported_detector(footless, cfg) is None
    assert exported_detector(footless, DetectorConfig(feet=["left_foot", "right_foot"])) == meta
    (tmp_path / "policy.json").write_text(json.dumps({"robot": "biped20", "fall_detector": None}))
    with pytest.raises(DeployError, match=r"exported without a fall detector \(robot 'biped20' names no feet\); export it"):
        FallDetector.load(tmp_path)
    bad = {**meta, "settings": {**meta["settings"], "contact_height": -0.01}}
    with pytest.raises(DeployError, match=r"^fall_detector.settings.contact_height: -0.01 is not a valid value$"):
        FallDetector(bad)
    with pytest.raises(DeployError, match=r"^fall_detector: format 0 is not 1"):
        FallDetector({**meta, "format": 0})
    det = FallDetector(meta)
    state = RobotState(base_quat=[1.0, 0.0, 0.0, 0.0], base_ang_vel=[0.0] * 3, base_lin_vel=[0.0, math.nan, 0.0],
                       joint_pos=spec.nominal_q(), joint_vel=np.zeros(20))  # fmt: skip
    with pytest.raises(DeployError, match=r"^state.base_lin_vel\[1\] is nan \(not finite\)$"):
        det.update(state)


def test_mode_detect_writes_its_report(tmp_path):
    r = fallkit_cli("mode=detect", "detector.pushes.count=24", "detector.pushes.after=0.5", f"hydra.run.dir={tmp_path}",
                    cwd=tmp_path)  # fmt: skip
    assert r.returncode == 0, r.stderr[-3000:]
    report = json.loads((tmp_path / "detection.json").read_text())
    t, sweep = report["table"], report["sweep"]
    assert t["pushes"] == 24 and 0 < t["falls"] < 24 and t["falls"] + t["survived"] == 24
    assert t["detected"] + t["missed_falls"] == t["falls"]
    assert "| pushes | falls | detected | missed falls |" in (tmp_path / "detection.md").read_text()
    # a higher threshold never detects more nor triggers falsely more often
    assert all(np.diff(sweep["detected"]) <= 0) and all(np.diff(sweep["false_triggers"]) <= 0)
    assert sweep["false_triggers"][0] > sweep["false_triggers"][-1]  # the sweep spans the trade-off
    for png in ("detection_roc.png", "detection_lead_time.png"):
        assert (tmp_path / png).stat().st_size > 10_000
