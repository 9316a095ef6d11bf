"""FallEnv overhead over the physics: env.step time vs the sim.step time inside it.

    .venv/bin/python benchmarks/env_step.py [--envs 256] [--steps 450] [--threads 0]

Runs `step_and_maybe_reset` (as a TorchRL collector does) with random actions on
the mujoco backend; every sim.step call inside is timed, so the overhead (reward
terms, observations, disturbances, TensorDict bookkeeping, resets) is measured on
the same steps (env_overhead_pct, target of issue 4: < 15). For reference it also
times a plain simulator without body kinematics (raw physics, as issue 6 counts
it) in alternating blocks: overhead_vs_raw_physics_pct. Medians over blocks.
Prints one JSON object on its last line.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time

import torch

from fallkit.api import get_robot
from fallkit.config import EnvConfig, RewardConfig
from fallkit.env.fall_env import FallEnv
from fallkit.poses.end_pose_set import random_end_poses
from fallkit.sim import make_sim


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--envs", type=int, default=256)
    p.add_argument("--steps", type=int, default=450, help="policy steps (150 per 3 s episode)")
    p.add_argument("--threads", type=int, default=0)
    args = p.parse_args()
    torch.set_num_threads(1)

    spec = get_robot("biped20")
    poses = random_end_poses(spec, 256, torch.Generator().manual_seed(0))
    sim = make_sim(spec, args.envs, "mujoco", threads=args.threads, body_state=True)
    env = FallEnv(spec, EnvConfig(), RewardConfig(), poses, sim, seed=0)

    # raw physics for reference: the same robot, no body kinematics, PD hold of random setpoints
    raw = make_sim(spec, args.envs, "mujoco", threads=args.threads)
    qpos, qvel = env.initial_states.sample(args.envs, torch.Generator().manual_seed(2))
    raw.reset(torch.arange(args.envs), qpos, qvel)

    sim_time = [0.0]
    step = sim.step

    def timed_step(targets):
        t = time.perf_counter()
        out = step(targets)
        sim_time[0] += time.perf_counter() - t
        return out

    sim.step = timed_step
    g = torch.Generator().manual_seed(1)
    j = len(spec.joints)
    td = env.reset()
    for _ in range(20):  # warm-up
        td["action"] = 0.3 * torch.randn(args.envs, j, generator=g)
        _, td = env.step_and_maybe_reset(td)
        raw.step(env.setpoint(td["action"]))

    # alternate blocks of env steps and raw sim steps, so machine load hits both alike
    block = 50
    env_ms, inner_ms, raw_ms = [], [], []
    for _ in range(max(1, args.steps // block)):
        actions = 0.3 * torch.randn(block, args.envs, j, generator=g)
        sim_time[0] = 0.0
        t0 = time.perf_counter()
        for a in actions:
            td["action"] = a
            _, td = env.step_and_maybe_reset(td)
        env_ms.append(1e3 * (time.perf_counter() - t0) / block)
        inner_ms.append(1e3 * sim_time[0] / block)
        targets = [env.setpoint(a) for a in actions]
        t0 = time.perf_counter()
        for q in targets:
            raw.step(q)
        raw_ms.append(1e3 * (time.perf_counter() - t0) / block)

    med = statistics.median
    overhead = [e - i for e, i in zip(env_ms, inner_ms)]
    result = {
        "envs": args.envs,
        "steps": len(env_ms) * block,
        "load_average_1min": os.getloadavg()[0],
        "cpu_count": os.cpu_count(),
        "env_step_ms": med(env_ms),
        "sim_step_ms": med(inner_ms),
        "raw_sim_step_ms": med(raw_ms),
        "env_overhead_ms": med(overhead),
        "env_overhead_pct": 100.0 * med([o / i for o, i in zip(overhead, inner_ms)]),
        "overhead_vs_raw_physics_pct": 100.0 * med([(e - r) / r for e, r in zip(env_ms, raw_ms)]),
        "env_steps_per_s": args.envs / (med(env_ms) / 1e3),
        "unstable": env.num_unstable,
    }
    print(json.dumps(result))


if __name__ == "__main__":
    main()
