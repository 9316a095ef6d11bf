"""Two trainings on one machine: does each get its share of the cores? (issue 19, item 9)

Runs one `train=quick` training alone, then `--jobs` of them side by side (same overrides,
seeds 0, 1, …), each for `--seconds`, and compares iterations per minute: 60 s over the
median iteration time, an iteration's time being the trainer's own collect_s + update_s
from metrics.csv, skipping the first
`--skip` iterations (start-up, first-touch allocations), so process start-up and the final
evaluation do not count. On a machine with C cores, N jobs side by side can each reach at
most 1/N of one job alone (when one job already uses every core):

  min_share   the slowest side-by-side job's iterations/min over the lone job's
              (target >= 0.45 for two jobs: each gets its half, minus little)

    python benchmarks/parallel_runs.py [--seconds 120] [--jobs 2] [--stagger S] [-- key=value …]

`--stagger S` starts each later run S seconds after the previous one: the first has then
sized its pools while alone and must give cores back. The runs then overlap only partly,
which is why the rate is taken from the median iteration time: keep the stagger under half
of `--seconds`, so that most iterations of every run ran side by side.

Overrides after `--` go to every training (e.g. `-- sim.threads=1`). The last line is one
JSON object. Nothing else may run on the machine meanwhile.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def start(run_dir: Path, seed: int, args: argparse.Namespace) -> subprocess.Popen:
    cmd = [
        sys.executable, "-m", "fallkit", "robot=biped20", "train=quick", f"train.max_minutes={args.seconds / 60:.4f}",
        "train.evaluate=false", f"seed={seed}", f"hydra.run.dir={run_dir}", *args.overrides,
    ]  # fmt: skip
    log = open(run_dir.parent / f"{run_dir.name}.log", "w")
    return subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env={**os.environ, "PYTHONUNBUFFERED": "1"})


def rate(run_dir: Path, skip: int) -> dict:
    """Iterations per minute of one finished run, from its own per-iteration timings."""
    rows = list(csv.DictReader((run_dir / "metrics.csv").open()))[skip:]
    if not rows:
        raise SystemExit(f"{run_dir}: fewer than {skip + 1} iterations; raise --seconds")
    seconds = [float(r["collect_s"]) + float(r["update_s"]) for r in rows]
    return {
        "iterations": len(rows),
        "it_per_min": 60.0 / statistics.median(seconds),
        "median_collect_s": statistics.median(float(r["collect_s"]) for r in rows),
        "median_update_s": statistics.median(float(r["update_s"]) for r in rows),
    }


def run_together(n: int, args: argparse.Namespace, root: Path, name: str) -> list[dict]:
    dirs = [root / f"{name}{i}" for i in range(n)]
    for d in dirs:
        d.mkdir(parents=True)
    procs = []
    for i, d in enumerate(dirs):
        if i and args.stagger:
            time.sleep(args.stagger)  # the first run has started alone and sized its pools to every core
        procs.append(start(d, i, args))
    for p, d in zip(procs, dirs):
        if p.wait() != 0:
            raise SystemExit(f"training failed, see {d.parent / (d.name + '.log')}")
    return [rate(d, args.skip) for d in dirs]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=120.0, help="training time of each run")
    ap.add_argument("--jobs", type=int, default=2, help="runs side by side")
    ap.add_argument("--stagger", type=float, default=0.0, help="start each later run this many seconds after the previous")
    ap.add_argument("--skip", type=int, default=3, help="first iterations left out")
    ap.add_argument("--out", type=Path, default=None, help="keep the runs here (default: a temporary folder)")
    ap.add_argument("overrides", nargs="*", help="Hydra overrides for every run (after --)")
    args = ap.parse_args()
    root = args.out or Path(tempfile.mkdtemp(prefix="fallkit_parallel_"))
    alone = run_together(1, args, root, "alone")[0]
    print(f"alone: {alone['it_per_min']:.1f} it/min")
    together = run_together(args.jobs, args, root, "together")
    shares = [t["it_per_min"] / alone["it_per_min"] for t in together]
    for i, (t, s) in enumerate(zip(together, shares)):
        print(f"side by side #{i}: {t['it_per_min']:.1f} it/min = {s:.2f} of alone")
    print(json.dumps({
        "benchmark": "parallel_runs", "jobs": args.jobs, "cores": os.cpu_count(), "seconds": args.seconds,
        "stagger_s": args.stagger, "overrides": args.overrides, "alone": alone, "together": together, "shares": shares,
        "min_share": min(shares), "target_min_share": round(0.9 / args.jobs, 3),
    }))  # fmt: skip


if __name__ == "__main__":
    main()
