"""One policy, both simulators: mode=eval of a checkpoint under sim=mujoco (MuJoCo C, float64)
and sim=warp (mujoco_warp, float32) on the same falls (issue 16, item 3).

Both evaluations draw the same initial states and end poses (same eval.seed and
eval.trials), so the policy's per-trial figures pair up; per metric the report gives both
means and the paired mean difference (warp − mujoco) with its 95 % interval
(mean ± 1.96·sd/√n). The interval holding 0 means the engines agree within the sampling
noise of n falls.

    python benchmarks/cross_backend.py CHECKPOINT [--trials 64] [--device cpu|cuda:0]

The last line is one JSON object (`max_diff_over_ci`: the largest |mean difference| over
its interval's half width, <= 1 where every metric agrees).
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
from pathlib import Path

import numpy as np
from fallkit_cli import fallkit

METRICS = ("max_impact_force", "fall_mean_impact_force", "mean_impact_force", "mroe", "mje", "rest_time")


def evaluate(checkpoint: str, backend: list[str], trials: int, out: Path) -> dict[str, np.ndarray]:
    fallkit("mode=eval", f"checkpoint={checkpoint}", f"eval.trials={trials}", "eval.seek_reference=false",
            f"hydra.run.dir={out}", *backend, quiet=True)  # fmt: skip
    with np.load(out / "eval_trials.npz") as z:
        return {m: z[f"policy/{m}"] for m in METRICS}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("checkpoint")
    ap.add_argument("--trials", type=int, default=64)
    ap.add_argument("--device", default="cpu", help="warp's device")
    args = ap.parse_args()
    root = Path(tempfile.mkdtemp(prefix="fallkit_cross_"))
    mj = evaluate(args.checkpoint, ["sim=mujoco"], args.trials, root / "mujoco")
    wp = evaluate(args.checkpoint, ["sim=warp", f"sim.device={args.device}"], args.trials, root / "warp")
    report, worst = {}, 0.0
    for m in METRICS:
        d = wp[m] - mj[m]
        half = 1.96 * float(d.std(ddof=1)) / math.sqrt(len(d))
        report[m] = {"mujoco_mean": float(mj[m].mean()), "warp_mean": float(wp[m].mean()), "diff_mean": float(d.mean()),
                     "diff_ci95_half": half, "agree": bool(abs(d.mean()) <= half)}  # fmt: skip
        worst = max(worst, abs(float(d.mean())) / half if half > 0 else 0.0)
        print(f"{m:24s} mujoco {mj[m].mean():9.4g}  warp {wp[m].mean():9.4g}  diff {d.mean():+.3g} ± {half:.3g}")
    print(json.dumps({"benchmark": "cross_backend", "checkpoint": args.checkpoint, "trials": args.trials,
                      "warp_device": args.device, "metrics": report, "max_diff_over_ci": worst}))  # fmt: skip


if __name__ == "__main__":
    main()
