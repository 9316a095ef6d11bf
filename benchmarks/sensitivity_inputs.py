"""One policy, many sensitivities (issue 17, part 1): what `robot.sensitivity.<c>=w` at evaluation does to
a policy trained with `env.sensitivity_inputs.enabled=true`.

Trains biped20 with the battery as its own component, every weight 1.0 (`robot=biped20_battery_baseline`),
on the battery experiment's CPU budget (`experiment=battery`: train=quick, 450 iterations, seed 0), with the
weights drawn per episode; then evaluates the same checkpoint three times on the same 512 falls (test split,
eval seed): at the robot's weights, with the head at 4x (4.0), and with the battery at 5.0 (the paper's
battery experiment, one conditioned policy instead of two trained ones). Targets: the head's 95th-percentile
max force falls by >= 25 % at 4x (`head_p95_reduction`); the battery's median and p95 fall at 5.0.

    python benchmarks/sensitivity_inputs.py [--out runs/sensitivity_inputs] [--checkpoint RUN]
        [--unconditioned RUN]   # e.g. experiments/battery/<time>/1_biped20_battery_baseline: the cost of
                                # conditioning at the default weights, against a policy of the same budget
        [--weighted RUN]        # e.g. experiments/battery/<time>/0_biped20_battery: the battery-5.0 policy
        [--poses FILE]          # pin the end-pose dataset (evaluations read the checkpoint's env.poses)
        [--minutes M]           # a wall-clock budget instead of 450 iterations
        [-- OVERRIDES…]         # training overrides, e.g. -- train.ppo.normalize_value=true

Prints one JSON object on its last line.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

ROBOT = "robot=biped20_battery_baseline"
TRAIN = [ROBOT, "train=quick", "train.iterations=450", "train.max_minutes=null", "eval.trials=512",
         "env.sensitivity_inputs.enabled=true", "seed=0"]  # fmt: skip
SETTINGS = {"default": [], "head_4x": ["robot.sensitivity.head=4.0"], "battery_5": ["robot.sensitivity.battery=5.0"]}


def fallkit(*overrides: str) -> None:
    subprocess.run([sys.executable, "-m", "fallkit", *overrides], check=True)


def summary(eval_json: Path) -> dict:
    """What this benchmark reads of an evaluation: tracking and the head's and battery's max force."""
    pol = json.loads(eval_json.read_text())["policy"]
    force = {c: pol["per_component"][c]["max_impact_force"] for c in ("head", "battery")}
    return {
        "mje": pol["mje"]["mean"], "mroe": pol["mroe"]["mean"], "max_impact": pol["max_impact_force"]["mean"],
        "head_p95": force["head"]["p95"], "head_median": force["head"]["median"],
        "battery_p95": force["battery"]["p95"], "battery_median": force["battery"]["median"],
    }  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="runs/sensitivity_inputs")
    ap.add_argument("--checkpoint", help="a run trained with env.sensitivity_inputs (skips the training)")
    ap.add_argument("--unconditioned", help="run dir of a policy of the same budget without sensitivity inputs")
    ap.add_argument("--weighted", help="run dir of a policy trained with the battery at 5.0 (robot=biped20_battery)")
    ap.add_argument("--poses", help="end-pose dataset to train and evaluate on (env.poses; default: the robot's)")
    ap.add_argument("--minutes", type=float, help="a wall-clock budget instead of the 450 iterations (train.max_minutes)")
    ap.add_argument("overrides", nargs=argparse.REMAINDER,
                    help="-- then training overrides (e.g. train.ppo.normalize_value=true)")
    args = ap.parse_args()
    extra = [o for o in args.overrides if o != "--"]
    out = Path(args.out) / time.strftime("%Y-%m-%d_%H-%M-%S")
    start = time.perf_counter()
    run = Path(args.checkpoint) if args.checkpoint else out / "train"
    if not args.checkpoint:
        budget = ["train.iterations=100000", f"train.max_minutes={args.minutes}"] if args.minutes else []
        fallkit(*TRAIN, *budget, *([f"env.poses={args.poses}"] if args.poses else []), *extra, f"hydra.run.dir={run}")
    train_s = time.perf_counter() - start
    results = {}
    for name, overrides in SETTINGS.items():
        where = out / f"eval_{name}"
        fallkit("mode=eval", ROBOT, f"checkpoint={run}", "eval.trials=512", *overrides, f"hydra.run.dir={where}")
        results[name] = summary(where / "eval.json")
    d, head, bat = results["default"], results["head_4x"], results["battery_5"]
    report = {
        "checkpoint": str(run),
        "overrides": extra,
        "train_seconds": round(train_s, 1),
        "seconds": round(time.perf_counter() - start, 1),
        "head_p95_reduction": round(1.0 - head["head_p95"] / d["head_p95"], 3),  # target >= 0.25
        "battery_median_ratio": round(bat["battery_median"] / max(d["battery_median"], 1e-9), 3),
        "battery_p95_ratio": round(bat["battery_p95"] / d["battery_p95"], 3),
        "evaluations": results,
    }
    for key, other in (("unconditioned", args.unconditioned), ("weighted", args.weighted)):
        if other:
            report[key] = summary(Path(other) / "eval.json")
    if args.unconditioned:
        u = report["unconditioned"]
        report["cost_at_default"] = {m: round(d[m] / u[m], 3) for m in ("mje", "mroe", "max_impact")}
    print(json.dumps(report))


if __name__ == "__main__":
    main()
