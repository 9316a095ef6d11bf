"""Root and joint accelerations per policy step vs at the worst physics substep (issue 14, B5).

The root_acc and joint_acc reward terms (paper Table I) use Δv / policy_dt over the 20 ms
policy step, while the contact force term takes the worst physics substep. This measures
how different the two would be on real falls: a policy (default: the shipped
examples/biped20_quick) falls `--trials` times from the evaluation's initial states in a
plain MuJoCo loop (fallkit.deploy.sim2sim's), and every policy step records ‖v̇_root‖² and
‖q̈‖² both ways. Reported: the means, their ratio (worst substep / step), the 99th
percentiles and the correlation of the two over all steps.

    python benchmarks/substep_acceleration.py [--run RUN_DIR] [--export DIR] [--trials 32]

`--run` gives the initial states and end poses (its config and eval seed); `--export` the
controller. The last line is one JSON object.
"""

from __future__ import annotations

import argparse
import json

import mujoco
import numpy as np

from fallkit.deploy import EndPose, FallController
from fallkit.deploy.sim2sim import _estimate, _fall_substep, _motor_model
from fallkit.eval.evaluate import make_eval_env, prepare
from fallkit.eval.rollout import draw_trials
from fallkit.rl.policy import load_policy
from fallkit.sim.base import Layout


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run", required=True, help="a training run (its eval seed, end poses and env)")
    ap.add_argument("--export", default="examples/biped20_quick")
    ap.add_argument("--trials", type=int, default=32)
    args = ap.parse_args()
    config = load_policy(args.run).config
    setup = prepare(config.model_copy(update={"checkpoint": args.run}))
    env = make_eval_env(setup, args.trials, None, config.eval.seed)
    trials = draw_trials(env, args.trials, config.eval.seed)
    spec, controller = env.spec, FallController.load(args.export)
    model, lay = _motor_model(spec), Layout(spec)
    data = mujoco.MjData(model)
    v, jv = lay.root_qvel, lay.joint_qvel.numpy()
    rec = {k: [] for k in ("root_step", "root_sub", "joint_step", "joint_sub")}
    for i in range(args.trials):
        pose = int(trials.pose_ids[i])
        controller.reset(EndPose(joints=dict(zip(spec.joint_names, env.end_poses.joint_pos[pose].double().tolist())),
                                 root_quat=env.end_poses.root_quat[pose].double().tolist()))  # fmt: skip
        mujoco.mj_resetData(model, data)
        data.qpos[:], data.qvel[:] = trials.qpos[i].numpy(), trials.qvel[i].numpy()
        mujoco.mj_forward(model, data)
        for _ in range(env.max_steps):
            cmd = controller.step(_estimate(data, lay))
            root0, joint0, root_sub, joint_sub = data.qvel[v : v + 3].copy(), data.qvel[jv].copy(), 0.0, 0.0
            for _ in range(spec.substeps):
                r, j = data.qvel[v : v + 3].copy(), data.qvel[jv].copy()
                _fall_substep(model, data, lay, cmd)  # sim2sim's PD torques and mj_step
                root_sub = max(root_sub, float(np.sum(((data.qvel[v : v + 3] - r) / model.opt.timestep) ** 2)))
                joint_sub = max(joint_sub, float(np.sum(((data.qvel[jv] - j) / model.opt.timestep) ** 2)))
            rec["root_step"].append(float(np.sum(((data.qvel[v : v + 3] - root0) / spec.policy_dt) ** 2)))
            rec["joint_step"].append(float(np.sum(((data.qvel[jv] - joint0) / spec.policy_dt) ** 2)))
            rec["root_sub"].append(root_sub)
            rec["joint_sub"].append(joint_sub)
    a = {k: np.array(x) for k, x in rec.items()}
    out = {"benchmark": "substep_acceleration", "trials": args.trials, "steps": len(a["root_step"])}
    for part in ("root", "joint"):
        step, sub = a[f"{part}_step"], a[f"{part}_sub"]
        out[part] = {"mean_step": float(step.mean()), "mean_worst_substep": float(sub.mean()),
                     "ratio_of_means": float(sub.mean() / step.mean()), "p99_step": float(np.percentile(step, 99)),
                     "p99_worst_substep": float(np.percentile(sub, 99)), "correlation": float(np.corrcoef(step, sub)[0, 1])}  # fmt: skip
        print(f"{part}: mean {step.mean():.4g} per step vs {sub.mean():.4g} at the worst substep "
              f"({sub.mean() / step.mean():.2f}x), correlation {out[part]['correlation']:.2f}")  # fmt: skip
    print(json.dumps(out))


if __name__ == "__main__":
    main()
