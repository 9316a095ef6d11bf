"""mode=eval's outputs: eval.json (one object per strategy), eval.md (tables),
eval_trials.npz (every per-trial figure), the PNG plots of `fallkit.eval.plots`, and
the terminal table. With eval.poses=auto, eval.json's `end_pose_choice` and an eval.md
section compare the chosen end poses with random assignment (`fallkit.eval.choice`)."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from fallkit.eval import plots
from fallkit.eval.choice import choice_markdown
from fallkit.eval.metrics import TrialMetrics, summarize_trials
from fallkit.eval.rollout import POLICY, SEEK, gain_scales
from fallkit.eval.strategies import STRATEGIES

log = logging.getLogger(__name__)


def write_results(
    results: dict[str, TrialMetrics], components: list[str], info: dict, run_dir: Path, choice: dict | None = None,
    random: dict[str, TrialMetrics] | None = None,
) -> dict:  # fmt: skip
    """eval.json, eval.md, eval_trials.npz and the plots; returns the eval.json object.

    With eval.poses=auto, `results` are the chosen poses' falls, `choice` the comparison
    (`fallkit.eval.choice.compare`, eval.json's `end_pose_choice`) and `random` the same falls
    toward randomly assigned poses (eval_trials.npz `random/<strategy>/<figure>`).
    """
    summary = {
        name: {"gain_scale": gain_scales([name])[0], **summarize_trials(m, components)} for name, m in results.items()
    }
    written = {**summary, "end_pose_choice": choice} if choice is not None else summary
    (run_dir / "eval.json").write_text(json.dumps(written, indent=2))
    np.savez_compressed(
        run_dir / "eval_trials.npz",
        components=np.array(components),
        **{f"{s}/{key}": v for s, m in results.items() for key, v in m.arrays().items()},
        **{f"random/{s}/{key}": v for s, m in (random or {}).items() for key, v in m.arrays().items()},
    )
    title = f"{info['robot']}: {info['trials']} falls per strategy"
    # as in the statistics; a strategy none of whose falls stayed stable (a policy with NaN actions) has nothing to plot
    stable = {name: m.take(~m.unstable) for name, m in results.items() if not m.unstable.all()}
    for name in sorted(set(results) - set(stable)):
        log.error("every fall of %s went unstable (restarted by the simulator): left out of the plots", name)
    figures = plots.plot_all(stable, components, run_dir, title)
    (run_dir / "eval.md").write_text(markdown_report(summary, info, [f.name for f in figures], choice))
    unstable = {n: s["unstable_trials"] for n, s in summary.items() if s["unstable_trials"]}
    if unstable:
        log.warning("falls restarted by the simulator (unstable), per strategy: %s", unstable)
    return written


# ---- against the best standard strategy --------------------------------------------------

# ratio name -> metric: the policy's mean over the best standard strategy's mean (lower is better)
RATIOS = {
    "max_impact_ratio": "max_impact_force",
    "fall_mean_impact_ratio": "fall_mean_impact_force",
    "mroe_ratio": "mroe",
    "mje_ratio": "mje",
}


def ratios(summary: dict, name: str = POLICY) -> dict[str, float]:
    """`name`'s mean of each metric over the best (lowest) of the three standard strategies' means."""
    out = {}
    for key, metric in RATIOS.items():
        # a strategy whose every trial was unstable has no mean (nan): it cannot be the best
        means = [m for m in (summary[s][metric]["mean"] for s in STRATEGIES) if m == m]
        best = min(means, default=float("nan"))
        out[key] = summary[name][metric]["mean"] / best if best > 0 else float("nan")  # nan: nothing to compare
    return out


def ratio_line(summary: dict, name: str = POLICY) -> str:
    """One line a person reads: e.g. "policy / best strategy: max impact 0.91x, ..."."""
    r = ratios(summary, name)
    cells = ", ".join(f"{label} {r[key]:.2f}x" for key, label in _RATIO_LABELS.items())
    return f"{name} / best standard strategy: {cells} (lower is better)"


_RATIO_LABELS = {
    "max_impact_ratio": "max impact",
    "fall_mean_impact_ratio": "fall-phase mean impact",
    "mroe_ratio": "MROE",
    "mje_ratio": "MJE",
}


# ---- tables ------------------------------------------------------------------------------

_METRICS = [
    ("max_impact_force", "max impact [N]", "{:.0f}"),
    ("mean_impact_force", "mean impact [N]", "{:.0f}"),
    ("fall_mean_impact_force", "mean impact, fall phase [N]", "{:.0f}"),
    ("mroe", "MROE [rad]", "{:.2f}"),
    ("mje", "MJE [rad]", "{:.2f}"),
]


def _cells(s: dict, template: str) -> list[str]:
    """One cell per metric of strategy summary `s`: `template` filled with its mean, std, median and p95."""
    cells = []
    for key, _, fmt in _METRICS:
        v = s[key]
        cells.append(template.format(*(fmt.format(v[stat]) for stat in ("mean", "std", "median", "p95"))))
    return cells


def text_table(summary: dict) -> str:
    """A compact terminal table: mean ± std (median / p95) of each metric."""
    head = f"{'strategy':12s}" + "".join(f"{label:>30s}" for _, label, _ in _METRICS)
    lines = [head]
    for name, s in summary.items():
        lines.append(f"{name:12s}" + "".join(f"{c:>30s}" for c in _cells(s, "{} ± {} ({}/{})")))
    lines.append("cells: mean ± std (median/p95) over trials")
    return "\n".join(lines)


def markdown_report(summary: dict, info: dict, figures: list[str], choice: dict | None = None) -> str:
    """eval.md: what was run, the metric table, the end-pose choice (eval.poses=auto), per-component figures,
    the plots."""
    names = list(summary)
    out = [f"# Evaluation: {info['robot']}", ""]
    out += [
        f"- policy: `{info['checkpoint']}`" if info["checkpoint"] else "- policy: none (standard strategies only)",
        f"- {info['trials']} falls per strategy, {info['seconds']:.2f} s each, "
        f"the same initial states and end poses for every strategy (seed {info['seed']})",
        f"- end poses: {info['poses']}",
        f"- took {info['elapsed']:.1f} s",
        "",
        "## Metrics (paper Sec. V-B)",
        "",
        "mean ± std, then median / 95th percentile, over trials.",
        "",
        "| strategy | " + " | ".join(label for _, label, _ in _METRICS) + " | unstable |",
        "|---|" + "---|" * (len(_METRICS) + 1),
    ]
    for n in names:
        s = summary[n]
        out.append(f"| {_label(n)} | " + " | ".join(_cells(s, "{} ± {}<br>{} / {}")) + f" | {s['unstable_trials']} |")
    out += [""] + [f"- {ratio_line(summary, n)}" for n in (POLICY, SEEK) if n in summary]
    out += [
        "- seek (reference): no learning; setpoints move open-loop from the joints at the fall's start to",
        "  the target joints by the tracking blend u(t), nominal gains. Not one of the paper's strategies:",
        "  it shows what reaching the end pose costs and buys without learning.",
    ] if SEEK in summary else []
    out += [
        "",
        "- max impact: the largest contact force on any component during the fall (every physics substep).",
        "- mean impact: the maximum over components of the time-mean contact force on that component.",
        "  Once the robot lies still this is dominated by its resting weight, so the fall-phase column",
        "  averages only over the steps before the robot first comes to rest.",
        "- MROE: geodesic distance between the target root orientation, turned about the vertical to",
        "  match the robot, and the root orientation at the last step. MJE: mean |q − q̂| at the last step.",
        "",
    ]
    out += choice_markdown(choice, _label) if choice is not None else []
    out += ["## Per component: max impact force [N], median / 95th percentile", ""]
    out += _component_table(
        summary, names, lambda f: f"{f['max_impact_force']['median']:.0f} / {f['max_impact_force']['p95']:.0f}"
    )
    out += [
        "",
        "## Per component: fall-phase mean impact force [N], mean over falls",
        "",
        "The fall-phase mean above is, per fall, the largest of these. A policy trained with sensitivity weights",
        "trades load between components: what it keeps off the fragile ones, the others carry.",
        "",
    ]
    out += _component_table(summary, names, lambda f: f"{f['fall_mean_impact_force']['mean']:.1f}")
    out += ["", "## Plots", ""] + [f"![{f}]({f})" for f in figures] + [""]
    return "\n".join(out)


def _component_table(summary: dict, names: list[str], cell) -> list[str]:
    """One markdown row per strategy, one column per component; `cell` formats a component's figures."""
    comps = list(summary[names[0]]["per_component"])
    rows = ["| strategy | " + " | ".join(comps) + " |", "|---|" + "---|" * len(comps)]
    for n in names:
        rows.append(f"| {_label(n)} | " + " | ".join(cell(summary[n]["per_component"][c]) for c in comps) + " |")
    return rows


def _label(name: str) -> str:
    return "seek (reference)" if name == SEEK else name


def main(argv: list[str] | None = None) -> None:
    """`python -m fallkit.eval.report <run dir or eval.json>`: the ratio lines of a finished evaluation."""
    import argparse
    import sys

    p = argparse.ArgumentParser(description=main.__doc__)
    p.add_argument("run", type=Path, help="a run directory with eval.json, or the eval.json itself")
    path = p.parse_args(argv).run
    path = path / "eval.json" if path.is_dir() else path
    if not path.is_file():
        print(f"fallkit: error: {path}: no eval.json here; evaluate with mode=eval checkpoint=<run> first", file=sys.stderr)
        sys.exit(2)
    summary = json.loads(path.read_text())
    for name in (POLICY, SEEK):
        if name in summary:
            print(ratio_line(summary, name))


if __name__ == "__main__":
    main()
