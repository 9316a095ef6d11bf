"""How long `FallController.step` takes on this CPU, one thread (issue 16, item 4).

Trains biped20 for one iteration with the default network (Table III: 3 × 512 ELU; the
weights do not change the time), exports it, and times `step` on the states of a real
fall (recorded once from the simulator, replayed in a loop), after a warm-up:

  step_median_ms  median time of one step [ms]
  step_p99_ms     99th percentile [ms]       (target <= 1 ms)

    python benchmarks/deploy_latency.py [--steps 20000] [--run DIR] [-- key=value …]

`--run` times an existing run's policy instead of training one; overrides after `--` go to
the one-iteration training (e.g. `-- robot=go1`). The last line is one JSON object.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np
from fallkit_cli import fallkit


def train_one_iteration(root: Path, overrides: list[str]) -> Path:
    run = root / "run"
    fallkit("train.iterations=1", "sim.num_envs=16", "train.num_steps=4", "train.evaluate=false", f"hydra.run.dir={run}",
            *overrides, quiet=True)  # fmt: skip
    return run


def recorded_states(run: Path, steps: int) -> list:
    """The states of one fall of the run's robot, as an estimator would report them."""
    import torch

    from fallkit.deploy import RobotState
    from fallkit.env.build import make_env
    from fallkit.eval.evaluate import eval_run_config
    from fallkit.rl.policy import load_policy
    from fallkit.rotations import quat_rotate_inverse

    policy = load_policy(run)
    env = make_env(eval_run_config(policy.config, None), policy.spec, split="test", seed=1, num_envs=1)
    td, states, names = env.reset(), [], policy.spec.joint_names
    for _ in range(min(steps, env.max_steps)):
        st = env.sim.state
        states.append(RobotState(
            base_quat=st.root_quat[0].tolist(), base_ang_vel=st.root_ang_vel[0].tolist(),
            base_lin_vel=quat_rotate_inverse(st.root_quat, st.root_lin_vel)[0].tolist(),
            joint_pos=dict(zip(names, st.joint_pos[0].tolist())), joint_vel=dict(zip(names, st.joint_vel[0].tolist())),
        ))  # fmt: skip
        with torch.no_grad():
            td = env.step(policy.module(td)).get("next")
    return states


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=20000)
    ap.add_argument("--run", type=Path, default=None, help="time this run's policy (default: train one)")
    ap.add_argument("overrides", nargs="*")
    args = ap.parse_args()
    root = Path(tempfile.mkdtemp(prefix="fallkit_latency_"))
    run = args.run or train_one_iteration(root, args.overrides)
    export = root / "export"
    export.mkdir(exist_ok=True)
    fallkit("mode=export", f"checkpoint={run}", f"hydra.run.dir={export}", quiet=True)
    states = recorded_states(run, 150)

    from fallkit.deploy import FallController

    controller = FallController.load(export)
    pose = sorted(controller.end_poses)[0] if controller.end_poses else None
    times = np.zeros(args.steps)
    for i in range(args.steps + 1000):  # 1000 warm-up steps
        if i % len(states) == 0:
            controller.reset(pose) if pose else controller.reset(_any_pose(controller))
        t0 = time.perf_counter_ns()
        controller.step(states[i % len(states)])
        if i >= 1000:
            times[i - 1000] = (time.perf_counter_ns() - t0) / 1e6
    meta = json.loads((export / "policy.json").read_text())
    result = {
        "benchmark": "deploy_latency", "robot": meta["robot"], "observation_size": meta["observation_size"],
        "steps": args.steps, "threads": 1, "cpu": _cpu(), "step_median_ms": float(np.median(times)),
        "step_p99_ms": float(np.percentile(times, 99)), "step_max_ms": float(times.max()), "target_p99_ms": 1.0,
    }  # fmt: skip
    print(f"controller.step: median {result['step_median_ms']:.3f} ms, p99 {result['step_p99_ms']:.3f} ms")
    print(json.dumps(result))


def _any_pose(controller):
    from fallkit.deploy import EndPose

    return EndPose(joints=dict(zip(controller.joint_names, controller.nominal.tolist())), ground="back")


def _cpu() -> str:
    """The CPU's model name (Linux), else the machine type."""
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
    except OSError:  # not Linux
        lines = []
    names = [line.split(":", 1)[1].strip() for line in lines if line.startswith("model name")]
    return names[0] if names else os.uname().machine


if __name__ == "__main__":
    main()
