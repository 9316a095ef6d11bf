"""One policy, many sensitivities (issue 17, part 1): what `robot.sensitivity.<c>=w` at evaluation does to
a policy trained with `env.sensitivity_inputs.enabled=true`.

Trains biped20 with the battery as its own component, every weight 1.0 (`robot=biped20_battery_baseline`),
on the battery experiment's CPU budget (`experiment=battery`'s train=quick iterations, read from the preset: 224 =
2.75 M env steps, as 450 of the 256-world train=quick this was first measured with; seed 0), with the
weights drawn per episode; then evaluates the same checkpoint three times on the same 512 falls (test split,
eval seed): at the robot's weights, with the head at 4x (4.0), and with the battery at 5.0 (the paper's
battery experiment, one conditioned policy instead of two trained ones). Targets: the head's 95th-percentile
max force falls by >= 25 % at 4x (`head_p95_reduction`); the battery's median and p95 fall at 5.0.

`head_p95_reduction_ci95` is its 95 % bootstrap interval: the falls resampled in pairs (the same fall at
1x and at 4x), 2000 times. At 512 falls the p95 rests on the worst 26 of them; `--trials 2048` narrows it.

`reading` says whether the policy reads its weight inputs at all: along 256 of its own falls at the robot's
weights, how much the learned deviation (the MLP's share of the action) changes when the head's observed
weight is 4x, when every weight is 4x, and — for scale — when the end pose is another fall's, each relative
to the deviation's size, averaged over the fall.

`return_at_default` (with `--unconditioned`): both policies replayed on the same falls with the task's reward
switched on at the robot's weights — the return each earns by the reward the unconditioned policy was trained
for, per term (the impact term also per component), and the conditioned minus the unconditioned with its 95 %
bootstrap interval. It says whether the conditioned policy's behaviour at 1x, the baseline of
`head_p95_reduction`, is better or worse at the task than the policy trained at those weights alone.

    python benchmarks/sensitivity_inputs.py [--out runs/sensitivity_inputs] [--checkpoint RUN]
        [--unconditioned RUN]   # e.g. experiments/battery/<time>/1_biped20_battery_baseline, evaluated here on
                                # the same falls: the cost of conditioning at the default weights against a
                                # policy of the same budget, and the head at 4x against it at 1x
        [--weighted RUN]        # e.g. experiments/battery/<time>/0_biped20_battery: the battery-5.0 policy
        [--poses FILE]          # pin the end-pose dataset (evaluations read the checkpoint's env.poses)
        [--minutes M]           # a wall-clock budget instead of the battery experiment's iterations
        [--trials N]            # falls per evaluation (default 512; more falls, a tighter p95)
        [-- OVERRIDES…]         # training overrides, e.g. -- train.ppo.normalize_value=true

Prints one JSON object on its last line.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch
from fallkit_cli import fallkit

ROBOT = "robot=biped20_battery_baseline"
TRAIN = [ROBOT, "train=quick", "train.max_minutes=null", "eval.trials=512",  # iterations: battery_iterations()
         "env.sensitivity_inputs.enabled=true", "seed=0"]  # fmt: skip
SETTINGS = {"default": [], "head_4x": ["robot.sensitivity.head=4.0"], "battery_5": ["robot.sensitivity.battery=5.0"]}


def summary(eval_json: Path) -> dict:
    """What this benchmark reads of an evaluation: tracking and the head's and battery's max force."""
    pol = json.loads(eval_json.read_text())["policy"]
    force = {c: pol["per_component"][c]["max_impact_force"] for c in ("head", "battery")}
    return {
        "mje": pol["mje"]["mean"], "mroe": pol["mroe"]["mean"], "max_impact": pol["max_impact_force"]["mean"],
        "head_p95": force["head"]["p95"], "head_median": force["head"]["median"],
        "battery_p95": force["battery"]["p95"], "battery_median": force["battery"]["median"],
    }  # fmt: skip


def eval_falls(run: Path, falls: int, reward: bool = False):
    """The checkpoint's policy (`prepare`'s setup), an env of `falls` worlds built as its evaluation builds one —
    with the task's reward switched on if `reward` (the evaluation switches it off) — and `falls` falls of the
    eval seed."""
    from fallkit.env.build import make_env
    from fallkit.eval.evaluate import eval_run_config, prepare
    from fallkit.eval.rollout import draw_trials
    from fallkit.robots import robot_spec

    setup = prepare(fallkit_config(run))
    config = eval_run_config(setup.config, setup.config.eval.seconds)
    if reward:
        config = config.model_copy(update={"reward": setup.config.reward})
    env = make_env(config, robot_spec(config.robot), split=setup.split, seed=config.eval.seed, num_envs=falls,
                   poses=setup.poses)  # fmt: skip
    return setup, env, draw_trials(env, falls, config.eval.seed)


@torch.no_grad()
def reading(run: Path, falls: int = 256) -> dict:
    """How much the learned deviation moves with the observed weights, and with another end pose (see above)."""
    from fallkit.env.observations import actor_slices

    setup, env, trials = eval_falls(run, falls)
    net = setup.policy.module.net
    cols = actor_slices(env.spec, env.observes_sensitivity, env.observes_gravity)
    weights, head = cols["sensitivity"], cols["sensitivity"].start + env.spec.component_names.index("head")
    goal = torch.cat([torch.arange(cols[n].start, cols[n].stop) for n in ("goal_root_quat", "goal_joint_pos")])
    other = torch.roll(torch.arange(falls), 1)  # each fall's end pose replaced by the previous fall's
    changes: dict[str, list[float]] = {"head_4x": [], "every_weight_4x": [], "another_end_pose": []}
    td = env.reset_to(trials.qpos, trials.qvel, trials.pose_ids)
    for _ in range(env.max_steps):
        obs = td["policy"]
        base = net.deviation(obs)
        size = base.norm(dim=-1).mean()
        if size > 0:  # not yet faded out
            variants = {"head_4x": obs.clone(), "every_weight_4x": obs.clone(), "another_end_pose": obs.clone()}
            variants["head_4x"][:, head] += math.log(4.0)
            variants["every_weight_4x"][:, weights] += math.log(4.0)
            variants["another_end_pose"][:, goal] = obs[other][:, goal]
            for name, o in variants.items():
                changes[name].append(((net.deviation(o) - base).norm(dim=-1).mean() / size).item())
        td = env.step(td.set("action", setup.policy(td.select("policy"))["action"]))["next"]
    return {name: round(sum(v) / len(v), 3) for name, v in changes.items()}


@torch.no_grad()
def task_return(run: Path, falls: int = 512) -> tuple[dict[str, np.ndarray], torch.Tensor]:
    """Each fall's return under the task's reward at the robot's weights — the reward a policy trained at those
    weights maximises; the evaluation switches it off — replayed on `falls` falls of the eval seed with the
    policy's mean action: per reward term (the impact term also per component), and the falls' initial states,
    so two policies' returns can be checked to pair."""
    setup, env, trials = eval_falls(run, falls, reward=True)
    td = env.reset_to(trials.qpos, trials.qvel, trials.pose_ids)
    columns = torch.zeros(falls, len(env.rewards.columns))
    for _ in range(env.max_steps):
        td = env.step(td.set("action", setup.policy(td.select("policy"))["action"]))["next"]
        columns += td["reward_terms"]
    out = {"return": columns.sum(dim=1).numpy()}
    for i, name in enumerate(env.rewards.columns):  # "impact/head": a component's share of the impact term
        term = name.split("/")[0]
        out[term] = out.get(term, 0.0) + columns[:, i].numpy()
        if "/" in name:
            out[name] = columns[:, i].numpy()
    return out, trials.qpos


def mean_difference_interval(x: np.ndarray, y: np.ndarray, draws: int = 2000) -> list[float]:
    """95 % bootstrap interval of mean(x − y), the falls resampled in pairs."""
    idx = np.random.default_rng(0).integers(0, len(x), size=(draws, len(x)))
    return [round(float(v), 2) for v in np.percentile((x - y)[idx].mean(axis=1), [2.5, 97.5])]


def p95_reduction_interval(default: Path, changed: Path, component: str = "head", draws: int = 2000) -> list[float]:
    """95 % bootstrap interval of 1 - p95(changed) / p95(default) of one component's max force, the same falls
    resampled in pairs; falls unstable in either evaluation are left out, as eval.json leaves them out."""
    a, b = np.load(default / "eval_trials.npz"), np.load(changed / "eval_trials.npz")
    if not np.array_equal(a["freeze/max_impact_force"], b["freeze/max_impact_force"]):  # a strategy: the falls
        sys.exit(f"sensitivity_inputs: {default} and {changed} did not evaluate the same falls (another dataset?)")
    c = list(a["components"]).index(component)
    ok = ~(a["policy/unstable"] | b["policy/unstable"])
    x, y = a["policy/component_max_force"][ok, c], b["policy/component_max_force"][ok, c]
    idx = np.random.default_rng(0).integers(0, len(x), size=(draws, len(x)))
    ratio = np.percentile(y[idx], 95, axis=1) / np.percentile(x[idx], 95, axis=1)
    return [round(float(v), 3) for v in np.percentile(1.0 - ratio, [2.5, 97.5])]


def fallkit_config(run: Path):
    """The evaluation config of a checkpoint, as `python -m fallkit mode=eval checkpoint=RUN ROBOT` composes it."""
    from fallkit.app import composed_config

    return composed_config("mode=eval", ROBOT, f"checkpoint={run}")


def battery_iterations() -> int:
    """The battery experiment's training iterations: this benchmark's budget, read from the one preset that sets it."""
    from fallkit.app import composed_config

    return composed_config("experiment=battery").train.iterations


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="runs/sensitivity_inputs")
    ap.add_argument("--checkpoint", help="a run trained with env.sensitivity_inputs (skips the training)")
    ap.add_argument("--unconditioned", help="run dir of a policy of the same budget without sensitivity inputs")
    ap.add_argument("--weighted", help="run dir of a policy trained with the battery at 5.0 (robot=biped20_battery)")
    ap.add_argument("--poses", help="end-pose dataset to train and evaluate on (env.poses; default: the robot's)")
    ap.add_argument("--minutes", type=float, help="a wall-clock budget instead of the battery experiment's iterations (train.max_minutes)")
    ap.add_argument("--trials", type=int, default=512, help="falls per evaluation (the same falls at every setting)")
    ap.add_argument("overrides", nargs=argparse.REMAINDER,
                    help="-- then training overrides (e.g. train.ppo.normalize_value=true)")
    args = ap.parse_args()
    for name in ("minutes", "trials"):
        value = getattr(args, name)
        if value is not None and value <= 0:
            ap.error(f"--{name} must be positive, got {value:g}")
    extra = [o for o in args.overrides if o != "--"]
    out = Path(args.out) / time.strftime("%Y-%m-%d_%H-%M-%S")
    start = time.perf_counter()
    run = Path(args.checkpoint) if args.checkpoint else out / "train"
    if not args.checkpoint:
        budget = (["train.iterations=100000", f"train.max_minutes={args.minutes}"] if args.minutes is not None
                  else [f"train.iterations={battery_iterations()}"])
        fallkit(*TRAIN, *budget, *([f"env.poses={args.poses}"] if args.poses else []), *extra, f"hydra.run.dir={run}")
    train_s = time.perf_counter() - start
    results = {}
    for name, overrides in SETTINGS.items():
        where = out / f"eval_{name}"
        fallkit("mode=eval", ROBOT, f"checkpoint={run}", f"eval.trials={args.trials}", *overrides, f"hydra.run.dir={where}")
        results[name] = summary(where / "eval.json")
    d, head, bat = results["default"], results["head_4x"], results["battery_5"]
    report = {
        "checkpoint": str(run),
        "overrides": extra,
        "train_seconds": round(train_s, 1),
        "seconds": round(time.perf_counter() - start, 1),
        "trials": args.trials,
        "head_p95_reduction": round(1.0 - head["head_p95"] / d["head_p95"], 3),  # target >= 0.25
        "head_p95_reduction_ci95": p95_reduction_interval(out / "eval_default", out / "eval_head_4x"),
        # null when the battery's median at the robot's weights is 0 (most falls do not touch it): no ratio
        "battery_median_ratio": round(bat["battery_median"] / d["battery_median"], 3) if d["battery_median"] else None,
        "battery_p95_ratio": round(bat["battery_p95"] / d["battery_p95"], 3),
        "reading": reading(run),
        "evaluations": results,
    }
    if args.weighted:
        report["weighted"] = summary(Path(args.weighted) / "eval.json")
    if args.unconditioned:  # evaluated here on the same falls, so both comparisons are paired
        where = out / "eval_unconditioned"
        fallkit("mode=eval", ROBOT, f"checkpoint={args.unconditioned}", f"eval.trials={args.trials}", f"hydra.run.dir={where}")
        report["unconditioned"] = u = summary(where / "eval.json")
        report["cost_at_default"] = {m: round(d[m] / u[m], 3) for m in ("mje", "mroe", "max_impact")}
        # the head at 4x against the policy trained at the robot's weights, at those weights (not the target's
        # comparison, which stays within the conditioned policy; see docs/sensitivity_inputs.md)
        report["head_p95_4x_vs_unconditioned"] = round(1.0 - head["head_p95"] / u["head_p95"], 3)
        report["head_p95_4x_vs_unconditioned_ci95"] = p95_reduction_interval(where, out / "eval_head_4x")
        # which of the two does the task at the robot's weights better, by its own reward (the baseline of
        # head_p95_reduction is the conditioned policy at 1x, not the unconditioned one)
        mine, at = task_return(run, args.trials)
        theirs, their_at = task_return(Path(args.unconditioned), args.trials)
        if not torch.equal(at, their_at):
            sys.exit(f"sensitivity_inputs: {run} and {args.unconditioned} replayed other falls (another dataset?)")
        report["return_at_default"] = {
            who: {k: round(float(v.mean()), 2) for k, v in r.items()} for who, r in (("conditioned", mine), ("unconditioned", theirs))
        }  # fmt: skip
        report["return_at_default"]["difference_ci95"] = mean_difference_interval(mine["return"], theirs["return"])
    print(json.dumps(report))


if __name__ == "__main__":
    main()
