"""`mode=eval`: falls under the standard strategies (and a policy), with impact figures.

All strategies see the same initial states (paired comparison): one simulator
holds `trials` worlds per strategy, and each block of worlds gets its
strategy's gain scale.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from fallkit.config import FallkitConfig
from fallkit.robots.spec import RobotSpec
from fallkit.samplers.initial_state import InitialStateConfig, InitialStateSampler
from fallkit.sim import make_sim
from fallkit.strategies import STRATEGIES

log = logging.getLogger(__name__)


@dataclass
class FallRecord:
    """Contact-force history summaries of many falls, per component [trials, C], newtons."""

    peak_force: np.ndarray  # max over the fall of |f_c| (every physics substep)
    mean_force: np.ndarray  # mean over the fall of |f_c| (policy steps, worst substep each)

    @property
    def max_impact_force(self) -> np.ndarray:
        """Paper: the largest contact force on any component during the fall [trials]."""
        return self.peak_force.max(axis=1)

    @property
    def mean_impact_force(self) -> np.ndarray:
        """Paper: the maximum over components of the mean contact force [trials]."""
        return self.mean_force.max(axis=1)


def rollout_strategies(
    spec: RobotSpec,
    trials: int,
    seconds: float,
    seed: int,
    initial_state: InitialStateConfig,
    sim_options: dict | None = None,
    show_progress: bool = True,
) -> dict[str, FallRecord]:
    """Fall `trials` times per standard strategy from the same initial states."""
    names = list(STRATEGIES)
    n = trials * len(names)
    sim = make_sim(spec, n, "mujoco", **(sim_options or {}))
    qpos, qvel = InitialStateSampler(spec, initial_state).sample(trials, torch.Generator().manual_seed(seed))
    sim.reset(torch.arange(n), qpos.repeat(len(names), 1), qvel.repeat(len(names), 1))
    sim.set_gain_scale(torch.tensor([STRATEGIES[s] for s in names]).repeat_interleave(trials))
    hold = sim.state.joint_pos.clone()  # "holding the most recent setpoint"
    steps = round(seconds * spec.policy_hz)
    C = len(spec.components)
    peak = torch.zeros(n, C)
    total = torch.zeros(n, C)
    for _ in tqdm(range(steps), desc="falls", unit="step", disable=not show_progress, leave=False):
        f = sim.step(hold).contact_force.norm(dim=-1)  # [n, S, C]
        worst = f.max(dim=1).values
        peak = torch.maximum(peak, worst)
        total += worst
    if sim.num_unstable:
        log.warning("%d unstable world(s) were reset during the evaluation", sim.num_unstable)
    out = {}
    for i, s in enumerate(names):
        rows = slice(i * trials, (i + 1) * trials)
        out[s] = FallRecord(peak_force=peak[rows].numpy(), mean_force=(total[rows] / steps).numpy())
    return out


def summary(values: np.ndarray) -> dict[str, float]:
    return {
        "mean": float(np.mean(values)),
        "std": float(np.std(values)),
        "median": float(np.median(values)),
        "p95": float(np.percentile(values, 95)),
    }


def run_eval(config: FallkitConfig, run_dir: Path) -> dict:
    spec = config.robot.spec()
    ev = config.eval
    if ev.checkpoint is not None:
        raise FileNotFoundError(f"eval.checkpoint: policies cannot be evaluated yet ({ev.checkpoint})")
    records = rollout_strategies(
        spec, ev.trials, ev.seconds, ev.seed, ev.initial_state, {"threads": config.sim.threads}
    )
    result = {
        name: {
            "max_impact_force": summary(r.max_impact_force),
            "mean_impact_force": summary(r.mean_impact_force),
            "per_component": {
                c: {"max": summary(r.peak_force[:, k]), "mean": summary(r.mean_force[:, k])}
                for k, c in enumerate(spec.components)
            },
        }
        for name, r in records.items()
    }
    (run_dir / "eval.json").write_text(json.dumps(result, indent=2))
    print(f"\n{spec.name}: {ev.trials} falls per strategy, {ev.seconds:g} s each, same initial states")
    print(f"{'strategy':12s} {'max impact [N] mean':>20s} {'median':>8s} {'p95':>8s} {'mean impact [N]':>16s}")
    for name, r in result.items():
        mx, mn = r["max_impact_force"], r["mean_impact_force"]
        print(f"{name:12s} {mx['mean']:20.0f} {mx['median']:8.0f} {mx['p95']:8.0f} {mn['mean']:16.0f}")
    print(f"\nresults: {run_dir / 'eval.json'}")
    return result
