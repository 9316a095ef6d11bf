"""What a training run learns in a wall-clock budget, judged by the paper's metrics (issue 13).

Trains biped20 with `train=quick` (with `--backend warp`: `sim=warp train=quick_gpu`, its GPU
sizing; `--train hour`: the CPU's hour-long preset) for `--minutes` per seed (default: the
preset's budget), exactly as the README's main job does (`python -m fallkit …`, which ends
by evaluating the final policy: 256 falls of the test split, eval seed, no noise or
disturbances, paired against the standard strategies on the same initial states and end poses),
then reads each run's eval.json and reports, per metric, the policy's mean over the best standard strategy's:

  max_impact_ratio        mean max impact force            (lower is better; target <= 0.85)
  mje_ratio               mean joint tracking error        (target <= 0.2)
  mroe_ratio              mean root orientation error      (target <= 0.75)
  fall_mean_impact_ratio  mean impact before coming to rest (target <= 0.95)

"seek" — setpoints blended from the fall's starting joints to the target joints by u(t),
no learning — is reported beside them as a reference, never counted as a strategy.

    python benchmarks/learning.py [--minutes 15] [--backend mujoco|warp] [--train quick] [--seeds 1] [--first-seed 0]
                                  [-- key=value …]

Extra Hydra overrides after `--` go to the training (e.g. `-- train.init_noise_std=0.5`), so
every change is measured the same way. The last line is one JSON object.
"""

from __future__ import annotations

import argparse
import csv
import json
import statistics
import time
from pathlib import Path

import yaml
from fallkit_cli import fallkit

from fallkit.eval.report import RATIOS, ratios
from fallkit.eval.rollout import SEEK


def train_and_evaluate(args, seed: int, run_dir: Path) -> dict:
    """One `python -m fallkit` training run (ending in its evaluation); its eval.json and log sizes."""
    # train=quick_gpu is train=quick sized for one GPU (4096 worlds in 4 big minibatches)
    preset = args.train or ("quick_gpu" if args.backend == "warp" else "quick")
    chosen = [f"train={preset}"] + (["sim=warp"] if args.backend == "warp" else [])
    if args.envs is not None:
        chosen.append(f"sim.num_envs={args.envs}")
    if args.minutes is not None:
        chosen.append(f"train.max_minutes={args.minutes}")
    started = time.monotonic()
    fallkit("robot=biped20", *chosen, f"seed={seed}", f"eval.trials={args.trials}", f"hydra.run.dir={run_dir}",
            *args.overrides)  # fmt: skip
    wall = time.monotonic() - started
    rows = list(csv.DictReader((run_dir / "metrics.csv").open()))
    resolved = yaml.safe_load((run_dir / "resolved_config.yaml").read_text())
    num_envs, steps = resolved["sim"]["num_envs"], resolved["train"]["num_steps"]
    return {
        "seed": seed,
        "preset": preset,
        "run_dir": str(run_dir),
        "eval": json.loads((run_dir / "eval.json").read_text()),
        "iterations": len(rows),
        "minutes": resolved["train"]["max_minutes"],
        "env_steps": len(rows) * num_envs * steps,
        "wall_s": wall,
    }


def all_ratios(summary: dict) -> dict:
    """Policy (and seek) over the best standard strategy, per metric, from one eval.json."""
    out = ratios(summary)
    if SEEK in summary:
        out.update({f"seek_{k}": v for k, v in ratios(summary, SEEK).items()})
    return out


def absolute(summary: dict) -> dict:
    """Each strategy's mean of each metric."""
    return {n: {m: round(s[m]["mean"], 4) for m in RATIOS.values()} for n, s in summary.items()}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--minutes", type=float, default=None, help="training budget per seed (default: the preset's)")
    p.add_argument("--backend", choices=("mujoco", "warp"), default="mujoco")
    p.add_argument("--train", default=None, help="the train= preset (default: quick, or quick_gpu on warp)")
    p.add_argument("--seeds", type=int, default=1, help="how many seeds, one training each")
    p.add_argument("--first-seed", type=int, default=0, help="seeds first … first + n − 1 (a second seed of a row)")
    p.add_argument("--envs", type=int, default=None, help="sim.num_envs (default: the preset's, 1024 or 4096 on warp)")
    p.add_argument("--trials", type=int, default=256, help="evaluation falls per strategy")
    p.add_argument("--out", default="runs/learning", help="run directories go here")
    p.add_argument("overrides", nargs="*", help="Hydra overrides for the training, after --")
    args = p.parse_args()
    for name in ("minutes", "seeds", "trials", "envs"):
        value = getattr(args, name)
        if value is not None and value <= 0:
            p.error(f"--{name} must be positive, got {value:g}")

    stamp = time.strftime("%Y-%m-%d_%H-%M-%S")
    seeds = range(args.first_seed, args.first_seed + args.seeds)
    runs = [train_and_evaluate(args, s, Path(args.out) / stamp / f"seed{s}") for s in seeds]
    per_seed = [{**all_ratios(r["eval"]), "seed": r["seed"], "iterations": r["iterations"]} for r in runs]
    result = {k: statistics.median(r[k] for r in per_seed) for k in per_seed[0] if k not in ("seed", "iterations")}
    result.update(
        backend=args.backend,
        train=runs[0]["preset"],
        minutes=runs[0]["minutes"],
        seeds=args.seeds,
        overrides=args.overrides,
        iterations=statistics.median(r["iterations"] for r in runs),
        env_steps=statistics.median(r["env_steps"] for r in runs),
        absolute=[absolute(r["eval"]) for r in runs],
        per_seed=per_seed,
        run_dirs=[r["run_dir"] for r in runs],
    )
    print(json.dumps(result))


if __name__ == "__main__":
    main()
