"""Evaluation throughput: a policy and the three standard strategies × N falls of biped20.

Target (issue 7): 1 024 falls each (4 096 falls of 3 s) in at most 2 minutes on a
2-core CPU, so the paper's 32 768 trials per strategy are practical.

The policy is the deployed controller's architecture (3×512 ELU MLP with its
observation normaliser, `fallkit.rl.policy.MeanAction`): untrained unless
--checkpoint is given, which changes the falls but not the cost. End poses are
random collision-free poses (`fallkit.env.fall_env.random_end_poses`), so the benchmark
does not need a pose dataset; they cost the same as dataset poses.

    .venv/bin/python benchmarks/eval_throughput.py [--trials 1024] [--num-envs 4096]

Last line: one JSON object with "seconds" (the evaluation itself) and "trials".
"""

from __future__ import annotations

import argparse
import json
import os
import time

import torch


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=1024, help="falls per strategy")
    ap.add_argument("--num-envs", type=int, default=4096, help="simulator worlds per chunk (all strategies)")
    ap.add_argument("--seconds", type=float, default=3.0, help="length of each fall [s]")
    ap.add_argument("--threads", type=int, default=0, help="MuJoCo threads, 0 = all cores")
    ap.add_argument("--torch-threads", type=int, default=1, help="torch CPU threads (mode=eval uses 1)")
    ap.add_argument("--checkpoint", default=None, help="a trained policy instead of an untrained network")
    ap.add_argument("--progress", action="store_true")
    args = ap.parse_args()

    from tensordict.nn import TensorDictModule

    from fallkit.api import get_robot
    from fallkit.config import FallkitConfig, TrainConfig
    from fallkit.env.fall_env import FallEnv
    from fallkit.eval.evaluate import eval_run_config
    from fallkit.eval.rollout import POLICY, chunking, draw_trials, evaluate
    from fallkit.eval.strategies import STRATEGIES
    from fallkit.poses.end_pose_set import random_end_poses
    from fallkit.rl.models import GaussianPolicyNet
    from fallkit.rl.policy import MeanAction, load_policy
    from fallkit.sim import make_sim

    torch.set_num_threads(args.torch_threads)
    t_setup = time.perf_counter()
    spec = get_robot("biped20")
    strategies = [POLICY, *STRATEGIES]
    k, chunks = chunking(args.trials, len(strategies), args.num_envs)
    # the env settings of mode=eval (no noise, disturbances or reward terms), random end poses
    cfg = eval_run_config(FallkitConfig(robot={"name": spec.name}), args.seconds)
    poses = random_end_poses(spec, 256, torch.Generator().manual_seed(0))
    sim = make_sim(spec, len(strategies) * k, threads=args.threads, body_state=True)
    env = FallEnv(spec, cfg.env, cfg.reward, poses, sim, seed=0)
    if args.checkpoint:
        policy = load_policy(args.checkpoint).module
    else:
        obs_dim = env.observation_spec["policy"].shape[-1]
        net = GaussianPolicyNet(obs_dim, len(spec.joints), TrainConfig().actor_hidden, 1.0).eval()
        policy = TensorDictModule(MeanAction(net), in_keys=["policy"], out_keys=["action"])
    trials = draw_trials(env, args.trials, 12345)
    setup = time.perf_counter() - t_setup

    t0, c0 = time.perf_counter(), time.process_time()
    results = evaluate(env, trials, strategies, policy, show_progress=args.progress)
    seconds, cpu = time.perf_counter() - t0, time.process_time() - c0

    falls = args.trials * len(strategies)
    steps = falls * env.max_steps
    out = {
        "seconds": round(seconds, 2),
        "trials": args.trials,
        "strategies": strategies,
        "falls": falls,
        "fall_seconds": args.seconds,
        "worlds": env.num_envs,
        "chunks": chunks,
        "setup_seconds": round(setup, 2),
        "cpu_seconds": round(cpu, 1),  # CPU time of all threads: less sensitive to other load than wall time
        "env_steps_per_second": round(steps / seconds),
        "physics_steps_per_second": round(steps * spec.substeps / seconds),
        "extrapolated_seconds_32768": round(seconds * 32768 / args.trials, 1),
        "target_seconds": 120.0,
        "unstable_falls": int(sum(m.unstable.sum() for m in results.values())),
        "torch_threads": torch.get_num_threads(),
        "cpu_count": os.cpu_count(),
        "load_average_1min": round(os.getloadavg()[0], 2),
    }
    print(
        f"{falls} falls ({args.trials} × {', '.join(strategies)}) of {args.seconds:g} s in {seconds:.1f} s "
        f"(1-min load average {out['load_average_1min']} on {out['cpu_count']} cores); "
        f"32 768 trials per strategy: about {out['extrapolated_seconds_32768'] / 60:.0f} min"
    )
    print(json.dumps(out))


if __name__ == "__main__":
    main()
