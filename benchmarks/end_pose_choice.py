"""The end pose chosen for the fall (issue 17, part 2): eval.poses=auto against random assignment.

A trained policy falls `--trials` times from mode=eval's initial states (its eval seed) three
ways on the same falls: toward randomly assigned candidates (draw_trials' shuffled cycle, what a
fixed eval.poses gives), toward the candidate its critic values most (`critic`), and toward the
candidate lying closest to where the fall is heading, its capture point (`heading`, the deployed
controller's choice). Reported per way: the policy's mean MJE, MROE and max impact (and the
same of zero torque, whose falls ignore the end pose: its MROE says how close the chosen poses
lie to where an uncontrolled fall ends), each difference with its paired 95 % interval.

    .venv/bin/python benchmarks/end_pose_choice.py --checkpoint runs/learning_default/<time>/seed0
        [--trials 256] [--candidates default] [--side back] [--scorers critic,heading]
        [--pivot-height 0.5]

The last line is one JSON object: random_mje, random_mroe, random_max_impact, then per scorer
auto_mje, auto_mroe, auto_max_impact (and *_diff_ci95), the time choosing took and how many
distinct poses were chosen.
"""

from __future__ import annotations

import argparse
import json
import time

import torch


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", required=True, help="a training run directory or checkpoint file")
    ap.add_argument("--trials", type=int, default=256, help="falls (each one per strategy and way)")
    ap.add_argument("--candidates", default=None, help="eval.candidates: null = the run's env.poses")
    ap.add_argument("--split", default="test")
    ap.add_argument("--side", default=None, help="eval.candidate_side, comma-separated (e.g. back)")
    ap.add_argument("--scorers", default="critic,heading")
    ap.add_argument("--pivot-height", type=float, default=None, help="eval.heading_pivot_height [m]")
    ap.add_argument("--num-envs", type=int, default=1024, help="simulator worlds per chunk")
    args = ap.parse_args()

    from fallkit.eval.choice import COMPARED, choose_end_poses, compare
    from fallkit.eval.evaluate import make_eval_env, prepare
    from fallkit.eval.rollout import POLICY, chunking, draw_trials, evaluate
    from fallkit.rl.policy import load_policy

    torch.set_num_threads(1)  # as mode=eval: the physics threads are MuJoCo's
    trained = load_policy(args.checkpoint).config
    heading = {} if args.pivot_height is None else {"heading_pivot_height": args.pivot_height}
    sides = args.side.split(",") if args.side else None
    strategies = [POLICY, "zero_torque"]
    results, out = {}, {"benchmark": "end_pose_choice", "checkpoint": args.checkpoint, "trials": args.trials}
    env = trials = random = None
    for scorer in args.scorers.split(","):
        ev = trained.eval.model_copy(update={
            "trials": args.trials, "split": args.split, "poses": "auto", "candidates": args.candidates,
            "candidate_side": sides, "scorer": scorer, **heading,
        })  # fmt: skip
        config = trained.model_copy(
            update={"checkpoint": args.checkpoint, "mode": "eval", "eval": type(ev).model_validate(ev.model_dump())}
        )
        setup = prepare(config)
        if env is None:  # one env and one random baseline for every scorer: the same falls throughout
            k, _ = chunking(args.trials, len(strategies), args.num_envs)
            env = make_eval_env(setup, len(strategies) * k, None, ev.seed)
            trials = draw_trials(env, args.trials, ev.seed)
            t0 = time.perf_counter()
            random = evaluate(env, trials, strategies, setup.policy, show_progress=False)
            out["evaluate_seconds"] = time.perf_counter() - t0
            out["candidates"] = len(env.end_poses)
        t0 = time.perf_counter()
        chosen = choose_end_poses(env, trials, setup.choice)
        choose_s = time.perf_counter() - t0
        auto = evaluate(env, chosen, strategies, setup.policy, show_progress=False)
        c = compare(
            random, auto, trials.pose_ids, chosen.pose_ids, env.end_poses, setup.choice, f"{len(env.end_poses)} poses"
        )
        results[scorer] = c
        row = c["strategies"][POLICY]
        out[scorer] = {"how": c["how"], "choose_seconds": choose_s, "distinct_chosen": c["distinct_chosen"],
                       "chosen_sides": c["chosen_sides"]}  # fmt: skip
        for key, short in (("mje", "mje"), ("mroe", "mroe"), ("max_impact_force", "max_impact"),
                           ("fall_mean_impact_force", "fall_mean_impact")):  # fmt: skip
            out[f"random_{short}"] = row[key]["random"]
            out[scorer][f"auto_{short}"] = row[key]["auto"]
            out[scorer][f"auto_{short}_diff_ci95"] = row[key]["diff_ci95"]
        out[scorer]["zero_torque_random_mroe"] = c["strategies"]["zero_torque"]["mroe"]["random"]
        out[scorer]["zero_torque_auto_mroe"] = c["strategies"]["zero_torque"]["mroe"]["auto"]

    print(f"{args.trials} falls, {out.get('candidates')} candidates" + (f" lying on {args.side}" if sides else ""))
    head = f"{'':24s}" + "".join(f"{lbl:>28s}" for _, lbl, _ in COMPARED)
    print(head)
    first = next(iter(results.values()))
    for name in strategies:
        print(
            f"{name + ' random':24s}"
            + "".join(f"{fmt.format(first['strategies'][name][k]['random']):>28s}" for k, _, fmt in COMPARED)
        )
        for scorer, c in results.items():
            cells = []
            for k, _, fmt in COMPARED:
                m = c["strategies"][name][k]
                cells.append(f"{fmt.format(m['auto'])} ({m['diff']:+.3g} ± {(m['diff_ci95'][1] - m['diff']):.2g})")
            print(f"{name + ' ' + scorer:24s}" + "".join(f"{cell:>28s}" for cell in cells))
    print(json.dumps(out))


if __name__ == "__main__":
    main()
