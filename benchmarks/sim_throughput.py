"""Physics throughput of fallkit's batch simulator against raw MuJoCo.

Both sides start from the same initial falling states (paper Table II), hold
the same joint setpoints and run the same number of physics steps on the same
model and number of threads, so the robots fall and then lie in contact:

  fallkit  MujocoSim.step: PD control, per-substep contact force per component,
           instability checks, torch state tensors
  raw      mujoco.batch.Batch.step(nstep=substeps): mj_step on the thread pool,
           no recording, no outputs (the physics limit of the machine)

Prints one JSON object on its last line; `ratio` = fallkit / raw (target >= 0.9).

    python benchmarks/sim_throughput.py [--worlds 256] [--steps 150] [--threads 0]
"""

from __future__ import annotations

import argparse
import json
import os
import time

import mujoco
import mujoco.batch
import numpy as np
import torch

from fallkit.api import get_robot
from fallkit.samplers.initial_state import InitialStateSampler
from fallkit.sim import make_sim


def time_fallkit(spec, qpos, qvel, targets, steps: int, threads: int) -> float:
    sim = make_sim(spec, len(qpos), "mujoco", threads=threads)
    sim.reset(torch.arange(len(qpos)), qpos, qvel)
    t = torch.as_tensor(targets, dtype=torch.float32)
    sim.step(t)  # warm-up (first call allocates)
    sim.reset(torch.arange(len(qpos)), qpos, qvel)
    start = time.perf_counter()
    for _ in range(steps):
        sim.step(t)
    return time.perf_counter() - start


def time_raw(spec, qpos, qvel, targets, steps: int, threads: int) -> float:
    model = spec.mj_model()
    batch = mujoco.batch.Batch(model, len(qpos), nthread=threads)

    def reset() -> None:
        batch.reset(stage=mujoco.mjtStage.mjSTAGE_NONE)
        batch.bind("qpos")[:] = qpos.numpy()
        batch.bind("qvel")[:] = qvel.numpy()
        batch.bind("ctrl")[:] = targets
        batch.forward()

    reset()
    batch.step(nstep=spec.substeps)
    reset()
    start = time.perf_counter()
    for _ in range(steps):
        batch.step(nstep=spec.substeps)
    return time.perf_counter() - start


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--robot", default="biped20")
    p.add_argument("--worlds", type=int, default=256)
    p.add_argument("--steps", type=int, default=150, help="policy steps (150 = 3 s: fall, then lie)")
    p.add_argument("--threads", type=int, default=0, help="0 = all cores")
    p.add_argument("--repeats", type=int, default=5)
    args = p.parse_args()
    torch.set_num_threads(1)  # the physics threads are MuJoCo's

    spec = get_robot(args.robot)
    qpos, qvel = InitialStateSampler(spec).sample(args.worlds, torch.Generator().manual_seed(0))
    targets = np.tile(spec.nominal_q(), (args.worlds, 1))
    physics_steps = args.worlds * args.steps * spec.substeps

    # Interleave the two so that machine noise (about ±10 % between identical runs
    # on a shared 2-core machine) hits both alike; the ratio is the median of the
    # per-pair ratios, the absolute figures the median of each side.
    fk, raw = [], []
    for _ in range(args.repeats):
        fk.append(time_fallkit(spec, qpos, qvel, targets, args.steps, args.threads))
        raw.append(time_raw(spec, qpos, qvel, targets, args.steps, args.threads))
    ratio = float(np.median(np.array(raw) / np.array(fk)))
    fallkit_sps = physics_steps / float(np.median(fk))
    raw_sps = physics_steps / float(np.median(raw))
    threads = args.threads or os.cpu_count()
    print(f"robot {args.robot}, {args.worlds} worlds x {args.steps} policy steps x {spec.substeps} substeps, {threads} threads")
    print(f"  raw MuJoCo (Batch.step):        {raw_sps:10.0f} physics steps/s")
    print(f"  fallkit MujocoSim.step:         {fallkit_sps:10.0f} physics steps/s")
    print(f"  ratio: {ratio:.3f} (median of {args.repeats} interleaved pairs; target >= 0.90)")
    print(json.dumps({
        "backend": "mujoco",
        "robot": args.robot,
        "worlds": args.worlds,
        "threads": threads,
        "raw_steps_per_s": round(raw_sps),
        "fallkit_steps_per_s": round(fallkit_sps),
        "ratio": round(ratio, 4),
    }))


if __name__ == "__main__":
    main()
