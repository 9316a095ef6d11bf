"""`mode=sim2sim checkpoint=<run>`: the exported controller in a plain MuJoCo loop, against mode=eval.

The policy is exported (`fallkit.rl.export`) and run by `fallkit.deploy.FallController`
as a robot would run it: one `MjData` stepped with `mj_step` at the physics rate, the
controller called at the policy rate with the state an estimator would give (base
orientation, base-frame velocities, joints by name), and the PD law applied by the loop
itself as torques (`tau = kp (setpoint − q) − kd q̇`, clipped to the torque limit) on
actuators that are plain motors — no fallkit simulator or environment in between. The
falls start from the evaluation's initial states toward its end poses (`eval.trials`,
`eval.seed`, `eval.split`: the same trials as `mode=eval`), and the paper's metrics of
both are reported side by side (sim2sim.json, sim2sim.md).

Agreement is judged per metric on the paired per-trial differences (loop − batch): the
two agree when the confidence interval of the mean difference, mean ± 2.64 · sd / √n (95 % for
the six metrics together, Bonferroni: at 1.96 each, a correct export would "disagree" somewhere in
about one run of four), holds 0, i.e. any difference is within what the sampling of n falls explains. Two
things legitimately differ: the loop's PD damping is explicit where MuJoCo's position
actuators under `implicitfast` integrate it implicitly, and the controller computes its
observation in float64 from MuJoCo's float64 state where the environment uses float32;
a fall is chaotic, so single falls drift apart while the means must not.

With eval.poses=auto both fall toward chosen end poses (docs/end_pose_choice.md): with
eval.scorer=heading the controller chooses each fall's pose itself from the estimate at the
fall's start (`FallController.choose_end_pose`), and the report counts how often it chose as
mode=eval did; the critic scorer needs privileged state, so the loop is given eval's choice.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from statistics import NormalDist

import mujoco
import numpy as np
import torch

from fallkit.config import FallkitConfig
from fallkit.deploy.controller import FallController
from fallkit.deploy.state import EndPose, RobotState
from fallkit.errors import ConfigError
from fallkit.eval.choice import PoseChoice, choose_end_poses
from fallkit.eval.evaluate import make_eval_env, prepare
from fallkit.eval.metrics import FallTrace, TrialMetrics, trial_metrics
from fallkit.eval.rollout import POLICY, Trials, draw_trials, evaluate
from fallkit.poses.end_pose_set import EndPoseSet
from fallkit.rl.export import run_export
from fallkit.robots.spec import RobotSpec
from fallkit.sim.base import Layout

METRICS = ("max_impact_force", "fall_mean_impact_force", "mean_impact_force", "mroe", "mje", "rest_time")


def run_sim2sim(config: FallkitConfig, run_dir: Path) -> dict:
    """`mode=sim2sim`: export, fall `eval.trials` times in both, compare, write and print the report."""
    if config.checkpoint is None:
        raise ConfigError("checkpoint: mode=sim2sim needs checkpoint=<run dir or checkpoint file>")
    torch.set_num_threads(1)
    export = run_dir / "export"
    export.mkdir(parents=True, exist_ok=True)
    run_export(config, export)
    setup, ev = prepare(config), config.eval
    env = make_eval_env(setup, min(ev.trials, config.sim.num_envs), ev.seconds, ev.seed)
    trials = draw_trials(env, ev.trials, ev.seed)
    run = setup.config  # a policy with sensitivity inputs runs with this run's weights, as mode=eval's does
    weights = run.robot.sensitivity if run.env.sensitivity_inputs.enabled else None
    controller, choice = FallController.load(export, sensitivity=weights), setup.choice
    if choice is not None:
        trials = choose_end_poses(env, trials, choice)
    batch = evaluate(env, trials, [POLICY], setup.policy)[POLICY]
    own = trials
    if choice is not None and choice.scorer == "heading":
        own = Trials(trials.qpos, trials.qvel, controller_choices(env.spec, controller, trials, env.end_poses, choice))
    loop = plain_mujoco_falls(env.spec, controller, own, env.end_poses, env.max_steps)
    report = compare(batch, loop)
    report["info"] = {"checkpoint": config.checkpoint, "trials": ev.trials, "seed": ev.seed, "seconds": env.max_steps * env.dt}
    if choice is not None:
        report["end_pose_choice"] = {
            "scorer": choice.scorer,
            "chosen_by": "the controller" if own is not trials else "mode=eval (privileged critic)",
            "same_as_eval": int((own.pose_ids == trials.pose_ids).sum()),
            "of": len(trials),
        }
    (run_dir / "sim2sim.json").write_text(json.dumps(report, indent=2))
    (run_dir / "sim2sim.md").write_text(markdown(report))
    print(markdown(report))
    return report


def plain_mujoco_falls(spec: RobotSpec, controller: FallController, trials: Trials, end_poses: EndPoseSet,
                       steps: int) -> TrialMetrics:  # fmt: skip
    """Every trial in one MjData with the controller in the loop; the paper's metrics per trial."""
    model = _motor_model(spec)
    data = mujoco.MjData(model)
    lay = Layout(spec)
    c, n = len(spec.components), len(trials)
    rec = {k: np.zeros((n, steps, c)) for k in ("peak", "mean")} | {k: np.zeros((n, steps)) for k in ("lin", "ang")}
    final_quat, final_q = np.zeros((n, 4)), np.zeros((n, len(spec.joints)))
    for i in range(n):
        pose = int(trials.pose_ids[i])
        controller.reset(EndPose(joints=dict(zip(spec.joint_names, end_poses.joint_pos[pose].double().tolist())),
                                 root_quat=end_poses.root_quat[pose].double().tolist()))  # fmt: skip
        mujoco.mj_resetData(model, data)
        data.qpos[:] = trials.qpos[i].numpy()
        data.qvel[:] = trials.qvel[i].numpy()
        mujoco.mj_forward(model, data)
        for t in range(steps):
            command = controller.step(_estimate(data, lay))
            forces = [_fall_substep(model, data, lay, command) for _ in range(spec.substeps)]
            rec["peak"][i, t], rec["mean"][i, t] = np.max(forces, axis=0), np.mean(forces, axis=0)
            rec["lin"][i, t] = np.linalg.norm(data.qvel[lay.root_qvel : lay.root_qvel + 3])
            rec["ang"][i, t] = np.linalg.norm(data.qvel[lay.root_qvel + 3 : lay.root_qvel + 6])
        final_quat[i] = data.qpos[lay.root_qpos + 3 : lay.root_qpos + 7]
        final_q[i] = data.qpos[lay.joint_qpos.numpy()]
    f = torch.from_numpy
    trace = FallTrace(
        peak_force=f(rec["peak"]), mean_force=f(rec["mean"]), root_lin_speed=f(rec["lin"]), root_ang_speed=f(rec["ang"]),
        final_root_quat=f(final_quat), final_joint_pos=f(final_q),
        target_root_quat=end_poses.root_quat[trials.pose_ids].double(),
        target_joint_pos=end_poses.joint_pos[trials.pose_ids].double(), unstable=torch.zeros(n, dtype=torch.bool),
    )  # fmt: skip
    return trial_metrics(trace, spec.policy_dt)


def controller_choices(spec: RobotSpec, controller: FallController, trials: Trials, end_poses: EndPoseSet,
                       choice: PoseChoice) -> torch.Tensor:  # fmt: skip
    """Each fall's end pose [n] (rows of end_poses), as the controller chooses it from the estimate at the start."""
    names = [f"candidate_{i}" for i in range(len(end_poses))]
    controller.add_end_poses({
        n: EndPose(joints=dict(zip(spec.joint_names, q.tolist())), root_quat=quat.tolist())
        for n, q, quat in zip(names, end_poses.joint_pos.double().cpu(), end_poses.root_quat.double().cpu())
    })  # fmt: skip
    model, lay = spec.mj_model(), Layout(spec)
    data = mujoco.MjData(model)
    row = {n: i for i, n in enumerate(names)}
    chosen = torch.empty(len(trials), dtype=torch.long)
    for i in range(len(trials)):
        data.qpos[:], data.qvel[:] = trials.qpos[i].numpy(), trials.qvel[i].numpy()  # all an estimate reads
        chosen[i] = row[controller.choose_end_pose(_estimate(data, lay), names, None, choice.pivot_height)]
    return chosen


def _motor_model(spec: RobotSpec) -> mujoco.MjModel:
    """The robot's scene with its position servos turned into plain torque motors (ctrl = torque)."""
    model = spec.mj_model().__copy__()
    model.actuator_gainprm[:] = 0.0
    model.actuator_gainprm[:, 0] = 1.0
    model.actuator_biasprm[:] = 0.0
    model.actuator_ctrllimited[:] = 0
    return model


def _estimate(data: mujoco.MjData, lay: Layout) -> RobotState:
    """What a perfect state estimator reports: base orientation, base-frame velocities, joints."""
    r, v = lay.root_qpos, lay.root_qvel
    quat = data.qpos[r + 3 : r + 7]
    lin_world = data.qvel[v : v + 3]
    base_lin = np.zeros(3)
    mujoco.mju_rotVecQuat(base_lin, lin_world, quat * np.array([1.0, -1.0, -1.0, -1.0]))  # world -> base
    return RobotState(
        base_quat=quat.tolist(), base_ang_vel=data.qvel[v + 3 : v + 6].tolist(), base_lin_vel=base_lin.tolist(),
        joint_pos=data.qpos[lay.joint_qpos.numpy()], joint_vel=data.qvel[lay.joint_qvel.numpy()],
    )  # fmt: skip


def _fall_substep(model: mujoco.MjModel, data: mujoco.MjData, lay: Layout, command) -> np.ndarray:
    """The loop's PD law as torques, one mj_step; the contact force magnitude per component [C]."""
    q, qd = data.qpos[lay.joint_qpos.numpy()], data.qvel[lay.joint_qvel.numpy()]
    tau = command.kp * (command.setpoint - q) - command.kd * qd
    data.ctrl[:] = np.clip(tau, -command.torque_limit, command.torque_limit)
    mujoco.mj_step(model, data)
    sensors = data.sensordata[lay.sensor_adr.numpy()[:, None] + np.arange(3)]  # [bodies, 3]
    return np.linalg.norm(lay.component_sum.numpy() @ sensors, axis=-1)


# Six metrics are judged at once: each interval at 95 % would call a correct export "disagreeing" in
# about one run of four by chance alone. Bonferroni: all six intervals hold together with 95 %.
Z_FAMILY = NormalDist().inv_cdf(1.0 - 0.05 / (2 * len(METRICS)))  # 2.64


def compare(batch: TrialMetrics, loop: TrialMetrics) -> dict:
    """Per metric: both means, the paired mean difference with its interval (95 % for all metrics together),
    and agreement."""
    out = {}
    for name in METRICS:
        a, b = getattr(batch, name), getattr(loop, name)
        d = b - a
        half = Z_FAMILY * float(d.std(ddof=1)) / math.sqrt(len(d)) if len(d) > 1 else float("inf")
        out[name] = {
            "batch_mean": float(a.mean()), "sim2sim_mean": float(b.mean()), "diff_mean": float(d.mean()),
            "diff_ci95": [float(d.mean()) - half, float(d.mean()) + half], "agree": bool(abs(float(d.mean())) <= half),
            "median_abs_trial_diff": float(np.median(np.abs(d))),
        }  # fmt: skip
    return {"metrics": out, "all_agree": all(m["agree"] for m in out.values())}


def markdown(report: dict) -> str:
    """sim2sim.md: the metrics side by side, and with eval.poses=auto whose choice the loop fell toward."""
    rows = ["| metric | mode=eval (batch) | sim2sim (plain MuJoCo loop) | paired difference, 95 % CI (all 6 together) | agree |",
            "|---|---|---|---|---|"]  # fmt: skip
    for name, m in report["metrics"].items():
        lo, hi = m["diff_ci95"]
        rows.append(f"| {name} | {m['batch_mean']:.4g} | {m['sim2sim_mean']:.4g} | {m['diff_mean']:+.3g} "
                    f"[{lo:+.3g}, {hi:+.3g}] | {'yes' if m['agree'] else '**no**'} |")  # fmt: skip
    verdict = "agree within sampling noise" if report["all_agree"] else "DISAGREE: a bug in one of them"
    c = report.get("end_pose_choice")
    chose = [] if c is None else [
        "", f"End poses chosen by {c['scorer']} (eval.poses=auto), in the loop by {c['chosen_by']}: "
        f"the same pose as mode=eval in {c['same_as_eval']} of {c['of']} falls.",
    ]  # fmt: skip
    return "\n".join(["# sim2sim: the exported controller in a plain MuJoCo loop vs mode=eval", "", *rows, "",
                      f"All metrics {verdict}.", *chose])  # fmt: skip
