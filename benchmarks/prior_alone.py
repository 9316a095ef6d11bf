"""The policy's prior alone, with no learning, for several blend powers (issue 13).

An untrained policy is its prior (`fallkit.rl.models.JointPrior`): the measured joints held, blended
into the end pose's joints by u(t)^p (`train.prior_power`). This evaluates that prior exactly as
`mode=eval` evaluates a policy — 256 falls of the test split, eval seed, no noise or disturbances,
paired against the standard strategies on the same initial states and end poses — once per power,
and prints the four ratios over the best strategy with the mean rest time and the falls that first
come to rest within a second. Why: the prior is where learning starts, and what it does to a fall
before any learning (how stiff the joints are through the impact, whether the body crumples onto
its legs and rests there) is a property of the robot, so a new robot's power can be looked at
before an hour is spent training it.

    .venv/bin/python benchmarks/prior_alone.py [--powers 1 2 4 8] [--trials 256] [-- robot=biped20 …]

Hydra overrides after `--` compose the training config whose env is evaluated (`train=quick` first).
The last line is one JSON object: per power, the ratios, `rest_s` and `rest_within_1s`.
"""

from __future__ import annotations

import argparse
import json

import torch
from tensordict.nn import TensorDictModule

from fallkit.app import composed_config
from fallkit.errors import FallkitError
from fallkit.eval.evaluate import draw_trials, evaluate, make_eval_env, prepare
from fallkit.eval.metrics import summarize_trials
from fallkit.eval.report import RATIOS, ratios
from fallkit.eval.rollout import POLICY
from fallkit.eval.strategies import STRATEGIES
from fallkit.rl.models import JointPrior


def main() -> None:
    try:
        run()
    except FallkitError as exc:  # a bad override, a robot without end poses …: one line, as the CLI says it
        raise SystemExit(f"prior_alone.py: error: {exc}") from None


def run() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--powers", type=float, nargs="+", default=[1.0, 2.0, 4.0, 8.0])
    ap.add_argument("--trials", type=int, default=256)
    ap.add_argument("overrides", nargs="*", help="Hydra overrides of the training config (after --)")
    args = ap.parse_args()
    if any(p <= 0 for p in args.powers):
        raise SystemExit(f"--powers: every power must be > 0 (train.prior_power), got {args.powers}")
    torch.set_num_threads(1)  # the physics threads are MuJoCo's, as in mode=eval
    config = composed_config("train=quick", *args.overrides)
    config = config.model_copy(update={"eval": config.eval.model_copy(update={"trials": args.trials})})
    setup = prepare(config)
    strategies = [POLICY, *STRATEGIES]
    env = make_eval_env(setup, len(strategies) * args.trials, None, config.eval.seed)
    trials = draw_trials(env, args.trials, config.eval.seed)
    out: dict = {"robot": env.spec.name, "trials": args.trials, "powers": {}}
    print(f"{env.spec.name}, the prior alone over the best standard strategy, {args.trials} falls:")
    print(f"{'power':>6s}  " + "  ".join(f"{k:>22s}" for k in RATIOS) + "  rest [s]  rest within 1 s")
    for power in args.powers:
        prior = JointPrior(env.spec, config.env.action_scale, seek=True, fade=True, power=power)
        module = TensorDictModule(prior, in_keys=["policy"], out_keys=["action"])
        results = evaluate(env, trials, strategies, module, show_progress=False)
        summary = {name: summarize_trials(m, env.spec.component_names) for name, m in results.items()}
        rest = results[POLICY].rest_time
        row = {**ratios(summary), "rest_s": float(rest.mean()), "rest_within_1s": int((rest < 1.0).sum())}
        out["powers"][f"{power:g}"] = row
        print(f"{power:6g}  " + "  ".join(f"{row[k]:22.3f}" for k in RATIOS) + f"  {row['rest_s']:8.2f}  {row['rest_within_1s']:15d}")
    print(json.dumps(out))


if __name__ == "__main__":
    main()
