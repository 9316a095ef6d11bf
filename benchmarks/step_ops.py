"""Tensor operations and host reads of training's iteration (issue 15, the CPU proxy).

On a GPU every tensor operation is (at least) one kernel launch and every host read of a device
value (`.item()`, `bool(tensor)`, `nonzero`, a tensor used as a size) is a sync that stalls the
launch queue; both are what a CUDA graph removes and what "no host syncs inside the rollout"
forbids. On the CPU, torch's profiler counts them on the same code: this runs the trainer's own
collection (`Trainer.collect`: the actor, FallEnv's step_and_maybe_reset, the episode
statistics) from the trainer's first, staggered observation, so episodes end and restart as in
training, and reports per env step (one policy step of the whole batch):

  ops_per_step        aten operations called from Python (top-level: what launches kernels)
  host_reads_per_step aten::_local_scalar_dense, nonzero, item and is_nonzero calls (device -> host)
  ms_per_step         wall time of a profiled step, and of an unprofiled one
  top                 the operations called most often, per step

and per iteration, outside the collection: the host reads of the PPO update (`Trainer.learn`) and
of the logged figures (`Trainer.diagnostics`). The trainer reads those figures once per
iteration, with one `.tolist()` of them all (not an aten call: not counted).

The simulator's own work (MuJoCo C on the CPU, one CUDA graph with mujoco_warp) is not a torch
operation and is not counted.

    .venv/bin/python benchmarks/step_ops.py [--envs 256] [--steps 24] [-- overrides]

Prints one JSON object on its last line.
"""

from __future__ import annotations

import argparse
import json
import time

import torch
from torch.profiler import ProfilerActivity, profile

from fallkit.app import composed_config
from fallkit.rl.monitor import HOST_READ_OPS, host_reads, top_level_ops
from fallkit.rl.trainer import Trainer


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--envs", type=int, default=256)
    ap.add_argument("--steps", type=int, default=24, help="policy steps per profiled collection")
    ap.add_argument("--out", default="/tmp/fallkit_step_ops")
    ap.add_argument("overrides", nargs=argparse.REMAINDER, help="-- then config overrides")
    args = ap.parse_args()
    extra = [o for o in args.overrides if o != "--"]
    config = composed_config("train=quick", f"sim.num_envs={args.envs}", f"train.num_steps={args.steps}", *extra)
    torch.set_num_threads(1)  # as the trainer collects
    trainer = Trainer(config, args.out)
    n = args.steps
    trainer.learn(trainer.collect())  # warm: first resets, allocations, the optimizer's state
    t0 = time.perf_counter()
    batch = trainer.collect()
    plain_ms = (time.perf_counter() - t0) * 1e3 / n
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        t0 = time.perf_counter()
        trainer.collect()
        profiled_ms = (time.perf_counter() - t0) * 1e3 / n
    with profile(activities=[ProfilerActivity.CPU]) as update:
        trainer.learn(batch)
    with profile(activities=[ProfilerActivity.CPU]) as logging:
        trainer.diagnostics(batch)
    counts = top_level_ops(prof)
    host = sum(counts[name] for name in HOST_READ_OPS)
    report = {
        "envs": args.envs,
        "steps": n,
        "ops_per_step": round(sum(counts.values()) / n, 1),
        "host_reads_per_step": round(host / n, 2),
        "host_reads_per_update": host_reads(update),
        "host_reads_logging": host_reads(logging),
        "ms_per_step": round(plain_ms, 2),
        "ms_per_step_profiled": round(profiled_ms, 2),
        "top": {name: round(c / n, 1) for name, c in counts.most_common(15)},
        "overrides": extra,
    }
    print(json.dumps(report))


if __name__ == "__main__":
    main()
