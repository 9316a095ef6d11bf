"""`mode=detect`: the fall detector judged in simulation, on pushes of growing size (issue 17, part 3).

The protocol: the robot stands on the floor at its nominal pose under its PD controller (setpoints =
the nominal pose, the spec's gains), placed at the height where its lowest geom touches the floor
(fallkit.poses.checker, as mode=play stands it). After `detector.pushes.settle` seconds a constant
horizontal force acts on the pushed body's centre of mass for `duration` seconds (force = impulse /
duration, so the impulse is exact), from a random direction; push sizes grow evenly from 0 to
`max_impulse` over the trials. A trial is a **fall** when any body other than the feet touches the
floor within `horizon` (2 s) of the push's start; the survivors are watched `after` seconds longer
only to report which of them fall later.

It runs as the robot would: one `MjData` stepped by `mj_step` (MuJoCo's PD servos at the physics
rate), and at the policy rate the detector, built from the same dict that `mode=export` writes into
policy.json, reads a perfect estimator's RobotState (base orientation, base-frame velocities, joints).
A plain loop rather than fallkit's BatchSim because the fall is defined by the contacts of bodies
with the floor, which MuJoCo's contact list gives exactly (the BatchSim's per-component sensors sum
the feet with the rest of the legs and count self-contacts too); one thread does 512 pushes in about
25 s. The signals are recorded every update, so the threshold is swept afterwards
(fallkit.deploy.detection_report) by the detector's own rule, `first_trigger`; the detector run live
at the configured threshold must trigger at the very same update in every trial, which is checked.

Writes detection.json, detection.md, detection_roc.png and detection_lead_time.png into the run dir.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import mujoco
import numpy as np
import torch

from fallkit.config import FallkitConfig
from fallkit.config.detector import PushTestConfig
from fallkit.deploy.detection_report import PushRecord, analyse, markdown, plots
from fallkit.deploy.detector import FallDetector, first_trigger
from fallkit.deploy.state import RobotState
from fallkit.errors import ConfigError
from fallkit.poses.checker import PoseChecker
from fallkit.robots import robot_spec
from fallkit.robots.kinematics import detector_export
from fallkit.robots.spec import RobotSpec
from fallkit.sim.base import Layout


def run_detect(config: FallkitConfig, run_dir: Path) -> dict:
    """`mode=detect`: push, record, sweep the threshold, write and print the report."""
    torch.set_num_threads(1)  # one MjData: torch only places the robot
    spec = robot_spec(config.robot)
    meta = detector_export(spec, config.detector)
    detector = FallDetector(meta)
    record = push_trials(spec, detector, config.detector.pushes)
    check_live(record, detector.settings)
    report = analyse(record, detector.settings, config.detector.pushes)
    report["info"] = {"robot": spec.name, "feet": meta["feet"], "pushes": config.detector.pushes.model_dump(mode="json"),
                      "pushed_body": config.detector.pushes.body or spec.root_body}  # fmt: skip
    (run_dir / "detection.json").write_text(json.dumps(report, indent=2))
    (run_dir / "detection.md").write_text(markdown(report))
    plots(report, run_dir)
    print(markdown(report))
    return report


def push_trials(spec: RobotSpec, detector: FallDetector, pushes: PushTestConfig) -> PushRecord:
    """Every push of the protocol (module docstring), the detector watching live."""
    model = spec.mj_model()
    data = mujoco.MjData(model)
    lay = Layout(spec)
    body = _pushed_body(spec, model, pushes.body)
    standing = standing_qpos(spec)
    touches = _non_foot_floor(model, detector.meta["feet"])
    dt, substeps = spec.policy_dt, spec.substeps
    before = round(pushes.settle / dt)
    steps = before + round((pushes.horizon + pushes.after) / dt)
    push_substeps = max(1, round(pushes.duration / model.opt.timestep))
    n = pushes.count
    impulse = pushes.max_impulse * (np.arange(n) + 0.5) / n  # growing evenly, never exactly 0 or the maximum
    direction = np.random.default_rng(pushes.seed).uniform(-math.pi, math.pi, n)
    signals = np.full((3, n, steps), np.nan)
    contact, live = np.full(n, np.nan), np.full(n, -1)
    for i in range(n):
        force = impulse[i] / (push_substeps * model.opt.timestep)
        wrench = np.array([force * math.cos(direction[i]), force * math.sin(direction[i]), 0.0])
        mujoco.mj_resetData(model, data)
        data.qpos[:] = standing
        data.ctrl[:] = spec.nominal_q()  # the PD servos hold the nominal pose throughout
        mujoco.mj_forward(model, data)
        detector.reset()
        for k in range(steps):
            detector.update(estimate(data, lay))  # measures every update, also after it said "fall"
            s = detector.signals
            signals[:, i, k] = s.tilt, s.tilt_rate, s.capture_distance
            contact[i] = _step(model, data, body, wrench, (k - before) * substeps, push_substeps, substeps, touches)
            if not math.isnan(contact[i]):
                break
        live[i] = -1 if detector.trigger_step is None else detector.trigger_step
    time = (np.arange(steps) - before) * dt
    return PushRecord(impulse, direction, time, signals[0], signals[1], signals[2], contact, live)


def _step(model: mujoco.MjModel, data: mujoco.MjData, body: int, wrench: np.ndarray, first: int, push_substeps: int,
          substeps: int, touches: np.ndarray) -> float:  # fmt: skip
    """One policy step of physics (`first` = its first substep counted from the push's start); the time of
    the first non-foot floor contact in it [s from the push's start], NaN when there is none."""
    for s in range(first, first + substeps):
        data.xfrc_applied[body, :3] = wrench if 0 <= s < push_substeps else 0.0
        mujoco.mj_step(model, data)
        if data.ncon:
            g = data.contact.geom[: data.ncon]
            if (touches[g[:, 0], g[:, 1]]).any():
                return (s + 1) * model.opt.timestep
    return math.nan


def _non_foot_floor(model: mujoco.MjModel, feet: list[str]) -> np.ndarray:
    """[ngeom, ngeom] True for the pairs (floor, a geom of a body other than the feet), both ways round."""
    foot_ids = {model.body(f).id for f in feet}
    floor = model.geom("floor").id
    robot = np.array([model.geom_bodyid[g] not in foot_ids and model.geom_bodyid[g] != 0 for g in range(model.ngeom)])
    pairs = np.zeros((model.ngeom, model.ngeom), bool)
    pairs[floor, robot] = pairs[robot, floor] = True
    return pairs


def _pushed_body(spec: RobotSpec, model: mujoco.MjModel, name: str | None) -> int:
    name = name or spec.root_body
    try:
        return model.body(name).id
    except KeyError:
        raise ConfigError(f"detector.pushes.body: robot '{spec.name}' has no body '{name}'") from None


def standing_qpos(spec: RobotSpec) -> np.ndarray:
    """The nominal pose [nq] upright at the origin, facing +x, its lowest geom on the floor."""
    quat = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=torch.float64)
    joints = torch.as_tensor(spec.nominal_q(), dtype=torch.float64)[None]
    return PoseChecker(spec, chunk=1, threads=1).on_ground(quat, joints, clearance=0.0)[0][0].numpy()


def estimate(data: mujoco.MjData, lay: Layout) -> RobotState:
    """What a perfect state estimator reports: base orientation, base-frame velocities, joints in policy order.
    (sim2sim's twin; that module pulls in the evaluation stack, which this mode does not need.)"""
    r, v = lay.root_qpos, lay.root_qvel
    quat = data.qpos[r + 3 : r + 7]
    base_lin = np.zeros(3)
    mujoco.mju_rotVecQuat(base_lin, data.qvel[v : v + 3], quat * np.array([1.0, -1.0, -1.0, -1.0]))  # world -> base
    return RobotState(base_quat=quat.tolist(), base_ang_vel=data.qvel[v + 3 : v + 6].tolist(),
                      base_lin_vel=base_lin.tolist(), joint_pos=data.qpos[lay.joint_qpos.numpy()],
                      joint_vel=data.qvel[lay.joint_qvel.numpy()])  # fmt: skip


def check_live(record: PushRecord, settings) -> None:
    """The sweep's rule at the configured threshold must trigger where the live detector did, in every trial."""
    for i in range(len(record.impulse)):
        want = first_trigger(record.capture[i], record.tilt[i], settings.capture_margin, settings.max_tilt,
                             settings.confirm_steps)  # fmt: skip
        if want != record.live_trigger[i]:
            raise RuntimeError(f"push {i}: live detector triggered at update {record.live_trigger[i]}, the sweep at {want}")
