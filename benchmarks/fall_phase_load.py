"""Who carries the robot's weight in the fall phase, per strategy and policy (issue 13).

The fall-phase mean impact is the largest, over components, of a component's mean contact force from
the fall's start to its first rest (`fallkit.eval.metrics`). Over a phase that starts and ends near
rest the contacts carry the robot's weight m g (the vertical impulse is m g T whatever the policy does;
a hard landing concentrates part of it), so the figure is nearly m g times the share of the weight the
most-loaded component carries until the first rest. This reads a finished evaluation's per-fall results
and prints, per strategy: the fall-phase mean, how often each component is the most loaded, each
component's fall-phase mean force and its share of m g, what each carries while lying from the first
rest to the episode's end, the mean first rest and the falls resting within a second. No simulation:
it reads `eval_trials.npz` and `resolved_config.yaml` of a run (the robot's mass, the episode length).

    .venv/bin/python benchmarks/fall_phase_load.py RUN_DIR [RUN_DIR ...]   # e.g. runs/learning/<time>/seed0

A RUN_DIR may be a parent of the run (the first evaluated run below it is read). The last line is one
JSON object: per run, per strategy, `fall_mean_impact_force`, `most_loaded`, `fall_phase_force`,
`share_of_weight`, `lying_force`, `rest_s`, `rest_within_1s`.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import yaml

from fallkit.config import validate
from fallkit.errors import FallkitError
from fallkit.robots import robot_spec

GRAVITY = 9.81  # [m/s²]
LYING_MARGIN = 0.2  # [s]: a fall resting later than the episode's end minus this has no lying stretch to read


def evaluated_run(path: Path) -> Path:
    """The run directory at or below `path` holding an evaluation (eval_trials.npz)."""
    if (path / "eval_trials.npz").is_file():
        return path
    found = sorted(p.parent for p in path.rglob("eval_trials.npz"))
    if not found:
        raise FallkitError(f"{path}: no eval_trials.npz at or below it; give a run that was evaluated (mode=eval)")
    return found[0]


def loads(run: Path) -> dict[str, dict]:
    """Per strategy (and the policy), the weight-carrying figures of its evaluated falls."""
    config = validate(yaml.safe_load((run / "resolved_config.yaml").read_text()))
    weight = float(robot_spec(config.robot).mj_model().body_mass.sum()) * GRAVITY
    episode = config.eval.seconds or config.env.episode_length
    with np.load(run / "eval_trials.npz") as z:
        trials = {k: z[k] for k in z.files}
    components = [str(c) for c in trials["components"]]
    out = {}
    for strategy in sorted({k.split("/")[0] for k in trials if k.endswith("/fall_mean_impact_force")}):
        fall = trials[f"{strategy}/component_fall_mean_force"]  # [N, C]
        whole = trials[f"{strategy}/component_mean_force"]
        rest = trials[f"{strategy}/rest_time"]
        lies = rest < episode - LYING_MARGIN
        # the episode's mean minus the fall phase's part, over the time after the first rest
        lying = (whole * episode - fall * rest[:, None])[lies] / (episode - rest[lies])[:, None]
        out[strategy] = {
            "fall_mean_impact_force": round(float(trials[f"{strategy}/fall_mean_impact_force"].mean()), 1),
            "most_loaded": dict(zip(components, np.bincount(fall.argmax(1), minlength=len(components)).tolist())),
            "fall_phase_force": {c: round(float(v), 1) for c, v in zip(components, fall.mean(0))},
            "share_of_weight": {c: round(float(v) / weight, 3) for c, v in zip(components, fall.mean(0))},
            "lying_force": {c: round(float(v), 1) for c, v in zip(components, lying.mean(0))} if lies.any() else {},
            "rest_s": round(float(rest.mean()), 2),
            "rest_within_1s": int((rest < 1.0).sum()),
        }
    return {"weight_N": round(weight, 1), "episode_s": episode, "strategies": out}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path)
    args = parser.parse_args()
    result = {}
    try:
        for path in args.runs:
            run = evaluated_run(path)
            result[str(run)] = figures = loads(run)
            print(f"{run}  (m g {figures['weight_N']:.0f} N, episode {figures['episode_s']:g} s)")
            for name, f in figures["strategies"].items():
                top = max(f["most_loaded"], key=f["most_loaded"].get)
                lying = f"{f['lying_force'][top]:.1f} N" if f["lying_force"] else "-"
                print(f"  {name:12s} fall-phase mean {f['fall_mean_impact_force']:6.1f} N | most loaded: {top} in "
                      f"{f['most_loaded'][top]} falls, {f['fall_phase_force'][top]:.1f} N = {f['share_of_weight'][top]:.3f}"
                      f" of m g, lying {lying} | first rest {f['rest_s']:.2f} s, {f['rest_within_1s']} within 1 s")
    except (FallkitError, OSError) as exc:
        sys.exit(f"fall_phase_load: {exc}")
    print(json.dumps(result))


if __name__ == "__main__":
    main()
