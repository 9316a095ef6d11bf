"""Wall time of the end-pose generator (paper Sec. IV-C) at the paper's size.

Generates the 24 000 train + 2 000 test poses of biped20 with the default
`DatasetConfig` (the `mode=poses` defaults: seed 0, 1024 worlds, 6 x 8 bins,
tolerance 0.1) on the MuJoCo CPU backend, all threads, and reports the time.
Target: `seconds` <= 300 on the 2-core development machine.

The machine is shared, so the run also reports how loaded it was: the 1-minute
load average before and after, and a short probe of the raw physics rate
(mujoco.batch rollout of lying robots, before and after). Compare `seconds`
only between runs with similar probes.

`--out PATH` also writes the dataset (this is how the shipped
fallkit/robots/assets/biped20_poses.npz is made; `python -m fallkit mode=poses`
with the same settings writes the same poses).

    python benchmarks/pose_generation.py [--train 24000] [--test 2000] [--worlds 1024] [--seed 0] [--out PATH]
        [--min-share M] [--side-min-share S] [--targeted T]

Prints one JSON object on its last line: `seconds`, `poses` and the run's statistics, among
them `sides` (the share of the poses lying on each side) and `side_balance` (issue 14:
lying on the left and on the right each hold >= 3/4 of the share of lying on the front or
the back, i.e. side_balance >= 0.75).
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
from fallkit.config import DatasetConfig
from fallkit.poses.bins import side_shares
from fallkit.poses.checker import PoseChecker
from fallkit.poses.generator import EndPoseGenerator, _Candidates, to_dataset
from fallkit.poses.settle import settle


def physics_probe(spec, seconds: float = 3.0) -> float:
    """Raw MuJoCo steps/s of 256 robots lying on the floor, all threads (the machine's current speed)."""
    checker = PoseChecker(spec)
    qpos, joints = _Candidates(checker, torch.Generator().manual_seed(123), 0.04, block=256).take(256)
    lying = settle(spec, qpos).qpos.numpy()
    batch = mujoco.batch.Batch(spec.mj_model(), len(lying), nthread=0)
    qp, ctrl = batch.bind("qpos"), batch.bind("ctrl")
    batch.reset(stage=mujoco.mjtStage.mjSTAGE_NONE)
    qp[:] = lying
    ctrl[:] = joints.numpy()
    batch.forward()
    steps, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        batch.step(nstep=20)
        steps += 20 * len(lying)
    return steps / (time.perf_counter() - start)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--robot", default="biped20")
    ap.add_argument("--train", type=int, default=24000)
    ap.add_argument("--test", type=int, default=2000)
    ap.add_argument("--worlds", type=int, default=1024)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=None, help="also write the dataset here (.npz)")
    ap.add_argument("--min-share", type=float, default=None, help="dataset.min_share (default: DatasetConfig's)")
    ap.add_argument("--side-min-share", type=float, default=None, help="dataset.side_min_share (default: DatasetConfig's)")
    ap.add_argument("--targeted", type=float, default=None, help="dataset.targeted (default: DatasetConfig's)")
    args = ap.parse_args()
    torch.set_num_threads(1)  # the physics threads use the cores

    spec = get_robot(args.robot)
    knobs = {"min_share": args.min_share, "side_min_share": args.side_min_share, "targeted": args.targeted}
    extra = {k: v for k, v in knobs.items() if v is not None}
    cfg = DatasetConfig(train=args.train, test=args.test, num_worlds=args.worlds, seed=args.seed, **extra)
    load_before = os.getloadavg()[0]
    probe_before = physics_probe(spec)
    start = time.perf_counter()
    gen = EndPoseGenerator(spec, cfg, "mujoco", threads=0).run(progress=True)
    sides = side_shares(gen.root_quat)
    seconds = time.perf_counter() - start
    probe_after = physics_probe(spec)
    load_after = os.getloadavg()[0]
    if args.out:
        from fallkit.poses.dataset import save_dataset

        save_dataset(args.out, to_dataset(spec, gen, cfg, "mujoco"))
        print(f"dataset: {args.out} ({os.path.getsize(args.out) / 1e6:.2f} MB)")
    st = gen.stats
    result = {
        "seconds": round(seconds, 1),
        "poses": len(gen.joint_pos),
        "target_seconds": 300,
        "robot": spec.name,
        "train": args.train,
        "test": args.test,
        "drops": st["drops"],
        "drops_per_pose": round(st["drops"] / max(1, len(gen.joint_pos)), 2),
        "settled": st["settled"],
        "aborted_overfull": st["aborted_overfull"],
        "unsettled": st["unsettled"],
        "unstable": st["unstable"],
        "mean_settle_seconds": round(st["mean_settle_seconds"], 3),
        "uniformity": round(st["uniformity"], 3),
        "rare_bins": len(st["rare_bins"]),
        "physics_steps": st["physics_steps"],
        "physics_steps_per_s": round(st["physics_steps"] / seconds),
        "probe_steps_per_s_before": round(probe_before),
        "probe_steps_per_s_after": round(probe_after),
        "load_avg_1min_before": round(load_before, 2),
        "load_avg_1min_after": round(load_after, 2),
        "cpus": os.cpu_count(),
        "hist_before": st["hist_before"],
        "hist_after": st["hist_after"],
        "sides_before": dict(zip(st["sides"], st["sides_before"])),
        "sides_after": dict(zip(st["sides"], st["sides_after"])),
        "rare_sides": st["rare_sides"],
        "sides": {k: round(v, 4) for k, v in sides.items()},
        # issue 14: lying on the left / right each at least 3/4 of lying on the front / back
        "side_balance": round(min(sides["left"], sides["right"]) / max(sides["front"], sides["back"]), 3),
    }
    print(json.dumps(result))


if __name__ == "__main__":
    np.set_printoptions(linewidth=200)
    main()
