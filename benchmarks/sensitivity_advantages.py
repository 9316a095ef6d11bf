"""How loud a drawn sensitivity weight is in the actor's learning signal (issue 17, part 1; a diagnostic).

A policy trained with `env.sensitivity_inputs.enabled=true` learns from advantages summed over the reward
terms. If the episodes drawn with a heavy weight had advantages many times larger than the others, PPO's
per-minibatch normalisation would let them set the policy for every weight (multi-task RL's reason for
per-task normalisation, PopArt). This continues a trained run from its last checkpoint, collects a few
iterations' batches with its policy and draws exactly as training does, computes GAE with the run's own
critic (`PPO.advantages`), and splits the samples into quartiles of one component's drawn weight: per
quartile, the spread (std) of the summed advantage and of each reward term's. Nothing is learned or saved.

    python benchmarks/sensitivity_advantages.py RUN [--component head] [--batches 6]

Prints one JSON object on its last line: `advantage_std_ratio` (the largest quartile's spread over the
smallest's) and, per quartile, the weights it spans and the spreads.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import torch
import yaml

from fallkit.config import validate
from fallkit.env.observations import actor_slices
from fallkit.rl.trainer import Trainer


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path, help="a training run directory (resolved_config.yaml, checkpoints/last.pt)")
    ap.add_argument("--component", default="head", help="the component whose drawn weight splits the samples")
    ap.add_argument("--batches", type=int, default=6, help="iterations' batches to collect")
    args = ap.parse_args()
    last = args.run / "checkpoints" / "last.pt"
    if not last.is_file():
        raise SystemExit(f"{args.run}: no checkpoints/last.pt; give a training run directory")
    raw = yaml.safe_load((args.run / "resolved_config.yaml").read_text())
    if not raw["env"]["sensitivity_inputs"]["enabled"]:
        raise SystemExit(f"{args.run}: trained without env.sensitivity_inputs.enabled: no weights were drawn")
    raw["resume"], raw["train"]["iterations"] = str(last), 10**9  # continue its collection, never its training
    trainer = Trainer(validate(raw), Path(tempfile.mkdtemp()))
    spec, env = trainer.spec, trainer.env
    if args.component not in spec.component_names:
        raise SystemExit(f"--component {args.component}: not a component of {spec.name}: {', '.join(spec.component_names)}")
    # the critic's observation starts with the actor's, noiseless: its sensitivity part is ln w per component
    column = actor_slices(spec, True, env.observes_gravity)["sensitivity"].start + spec.component_names.index(args.component)
    advantages, terms, log_w = [], [], []
    for _ in range(args.batches):
        batch = trainer.collect()
        trainer.ppo.advantages(batch)
        advantages.append(batch["advantage"].reshape(-1))
        terms.append(batch["term_advantages"].flatten(0, -2) if "term_advantages" in batch.keys() else None)
        log_w.append(batch["critic"][..., column].reshape(-1))
    advantage, log_w = torch.cat(advantages), torch.cat(log_w)
    term = torch.cat(terms) if terms[0] is not None else None
    quartile = torch.bucketize(log_w, torch.quantile(log_w, torch.tensor([0.25, 0.5, 0.75])))
    rows = []
    for q in range(4):
        m = quartile == q
        row = {"weights": [round(float(log_w[m].min().exp()), 2), round(float(log_w[m].max().exp()), 2)],
               "samples": int(m.sum()), "advantage_std": round(float(advantage[m].std()), 3)}  # fmt: skip
        if term is not None:
            row["term_std"] = dict(zip(trainer.ppo.term_names, (round(v, 3) for v in term[m].std(0).tolist())))
        rows.append(row)
        print(f"{args.component} weight {row['weights'][0]:.2f}-{row['weights'][1]:.2f}: advantage std "
              f"{row['advantage_std']:.2f}" + (f"; per term {row['term_std']}" if term is not None else ""))  # fmt: skip
    spreads = [r["advantage_std"] for r in rows]
    print(json.dumps({"run": str(args.run), "component": args.component, "iteration": trainer.iteration,
                      "samples": int(advantage.numel()), "advantage_std_ratio": round(max(spreads) / min(spreads), 3),
                      "quartiles": rows}))  # fmt: skip


if __name__ == "__main__":
    main()
