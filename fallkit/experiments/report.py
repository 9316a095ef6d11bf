"""The report step of an experiment: its runs → one figure (PNG) and one table (markdown + JSON).

Runs at the end of `python -m fallkit -m experiment=<name>` (a Hydra callback, `ReportCallback`),
and again on existing run directories with `python -m fallkit.experiments <experiment dir>`.
It writes `<name>.png`, `report.md` and `report.json` into the experiment directory and says
plainly which jobs are missing or failed; the figures are drawn from the jobs that finished.
Each report also checks the direction of the paper's finding on its figures (`findings`),
so a reader sees at once what a small run reproduces and what it does not.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any, Callable

import matplotlib.pyplot as plt
import numpy as np
from hydra.experimental.callback import Callback
from omegaconf import DictConfig

from fallkit.errors import ConfigError
from fallkit.eval.metrics import summarize
from fallkit.eval.plots import save_figure, strategy_color
from fallkit.eval.report import ratios
from fallkit.eval.rollout import POLICY
from fallkit.eval.strategies import STRATEGIES
from fallkit.experiments.cross_eval import evaluation_on
from fallkit.experiments.runs import Experiment, Job, read_experiment

log = logging.getLogger(__name__)

COMPARED = [POLICY, *STRATEGIES]  # the paper's comparison: the policy and the three standard strategies


def _ms(s: dict[str, float]) -> str:
    return f"{s['mean']:.3f} ± {s['std']:.3f}"


def _table(header: list[str], rows: list[list[Any]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    return "\n".join(lines + ["| " + " | ".join(str(c) for c in row) + " |" for row in rows])


def _finding(claim: str, holds: bool | None, figures: str) -> dict[str, Any]:
    """The paper's claim, whether these runs agree in direction (None: too few runs or no clear trend)."""
    return {"claim": claim, "reproduced": holds, "figures": figures}


def _trend(x: np.ndarray, y: np.ndarray, sign: int) -> tuple[bool | None, str]:
    """Does y follow x with the given sign? A correlation below 0.5 in size is no clear trend (None)."""
    if len(x) < 3:
        return None, "n/a (fewer than 3 runs)"
    r = float(np.corrcoef(x, y)[0, 1])
    return (None if abs(r) < 0.5 else (r * sign > 0)), f"correlation {r:+.2f}"


# ---- 1. comparison with the standard strategies (fig:impact_force) ------------------------------------


def comparison(exp: Experiment, out: Path) -> dict[str, Any]:
    """Box plots of max and mean impact force per component, policy vs the three strategies,
    pooled over the finished jobs (seeds); stable falls only, as in every evaluation statistic."""
    pooled: dict[str, dict[str, list[np.ndarray]]] = {s: {"max": [], "mean": []} for s in COMPARED}
    components: list[str] = []
    for job in exp.done:
        trials = job.trials()
        components = [str(c) for c in trials["components"]]
        for s in COMPARED:
            stable = ~trials[f"{s}/unstable"].astype(bool)
            pooled[s]["max"].append(trials[f"{s}/component_max_force"][stable])
            pooled[s]["mean"].append(trials[f"{s}/component_mean_force"][stable])
    data = {s: {k: np.concatenate(v) for k, v in d.items()} for s, d in pooled.items()}
    _component_boxes(data, components, out)

    table = {
        c: {s: {k: summarize(data[s][k][:, i]) for k in ("max", "mean")} for s in COMPARED}
        for i, c in enumerate(components)
    }
    rows = [
        [c] + [f"{table[c][s]['max']['median']:.0f} / {table[c][s]['mean']['median']:.0f}" for s in COMPARED]
        for c in components
    ]
    best = {c: min(STRATEGIES, key=lambda s: table[c][s]["max"]["median"]) for c in components}
    lower = [c for c in components if table[c][POLICY]["max"]["median"] < table[c][best[c]]["max"]["median"]]
    worst = [c for c in components
             if all(table[c][POLICY]["max"]["p95"] < table[c][s]["max"]["p95"] for s in STRATEGIES)]  # fmt: skip
    overall = [ratios(j.summary) for j in exp.done]
    findings = [
        _finding(
            "the policy's max impact is lower than every standard strategy's, on every component",
            len(lower) == len(components),
            f"lower median max force on {len(lower)} of {len(components)} components ({', '.join(lower) or 'none'})",
        ),
        _finding(
            "the policy's worst cases (95th percentile of max force) are lower than every strategy's, per component",
            len(worst) == len(components),
            f"lower on {len(worst)} of {len(components)} components ({', '.join(worst) or 'none'})",
        ),
        _finding(
            "the policy's overall max impact is lower than the best strategy's",
            all(r["max_impact_ratio"] < 1 for r in overall),
            "max impact ratio per seed: " + ", ".join(f"{r['max_impact_ratio']:.3f}" for r in overall),
        ),
    ]
    md = _table(["component"] + [f"{s} max / mean [N] (median)" for s in COMPARED], rows)
    return {"table": table, "ratios": overall, "markdown": md, "findings": findings}


def _component_boxes(data: dict[str, dict[str, np.ndarray]], components: list[str], out: Path) -> None:
    """Max (top) and mean (bottom) impact force per component: one box per strategy, grouped."""
    fig, axes = plt.subplots(2, 1, figsize=(max(8, 2.2 * len(components)), 8))
    width = 0.8 / len(COMPARED)
    for ax, (key, label) in zip(axes, [("max", "max impact force [N]"), ("mean", "mean impact force [N]")]):
        for i, s in enumerate(COMPARED):
            pos = np.arange(len(components)) + (i - (len(COMPARED) - 1) / 2) * width
            box = ax.boxplot(
                [data[s][key][:, c] for c in range(len(components))], positions=pos, widths=width * 0.9,
                patch_artist=True, showfliers=False,
            )  # fmt: skip
            for patch in box["boxes"]:
                patch.set_facecolor(strategy_color(s))
            ax.plot([], [], "s", color=strategy_color(s), label=s.replace("_", " "))
        ax.set_xticks(np.arange(len(components)), components)
        ax.set_ylabel(label)
        ax.grid(axis="y", alpha=0.3)
    axes[0].legend(ncols=len(COMPARED), loc="upper right")
    falls = len(data[POLICY]["max"])
    save_figure(fig, out, f"Impact per component: policy vs standard strategies ({falls} falls)")


# ---- 2. impact vs tracking (fig:track_abl) -------------------------------------------------------------


def impact_tracking(exp: Experiment, out: Path) -> dict[str, Any]:
    """Mean max impact force against mean MJE, one labelled point per impact weight."""
    points = sorted(
        (
            float(j.value("reward.impact")),
            j.summary[POLICY]["max_impact_force"]["mean"],
            j.summary[POLICY]["mje"]["mean"],
            j.summary[POLICY]["mroe"]["mean"],
        )
        for j in exp.done
    )
    fig, ax = plt.subplots(figsize=(7, 5))
    w, impact, mje, mroe = (np.array(v) for v in zip(*points)) if points else ([],) * 4
    ax.plot(mje, impact, "-o", color=strategy_color(POLICY), label="policy")
    offsets = [(6, 4), (6, -12), (-28, 4), (-28, -12)]  # neighbours with near-equal figures stay readable
    for i, (wi, x, y) in enumerate(zip(w, mje, impact)):
        ax.annotate(f"{wi:g}", (x, y), textcoords="offset points", xytext=offsets[i % len(offsets)])
    if exp.done:  # the strategies do not depend on the reward: the same in every job
        for s in STRATEGIES:
            ref = exp.done[0].summary[s]
            ax.plot(ref["mje"]["mean"], ref["max_impact_force"]["mean"], "x", color=strategy_color(s), label=s)
    ax.set_xlabel("mean joint tracking error (MJE) [rad]")
    ax.set_ylabel("mean max impact force [N]")
    ax.grid(alpha=0.3)
    ax.legend()
    save_figure(fig, out, "Impact vs tracking: impact reward weight swept")

    rows = [[f"{a:g}", f"{b:.0f}", f"{c:.3f}", f"{d:.3f}"] for a, b, c, d in points]
    lower, r_impact = _trend(np.log(w), impact, -1)  # the weights are swept by factors: log scale
    higher, r_mje = _trend(np.log(w), mje, +1)
    findings = [
        _finding("a larger impact weight lowers the max impact force", lower, f"log weight vs max impact: {r_impact}"),
        _finding("a larger impact weight raises the joint tracking error", higher, f"log weight vs MJE: {r_mje}"),
    ]
    md = _table(["impact weight", "max impact [N] (mean)", "MJE [rad] (mean)", "MROE [rad] (mean)"], rows)
    return {"points": [dict(zip(("weight", "max_impact", "mje", "mroe"), p)) for p in points], "markdown": md,
            "findings": findings}  # fmt: skip


# ---- 3. generated vs artist training data (tab:tracking_eval) --------------------------------------------

SOURCES = {"default": "generated", "artist": "artist"}


def data_source(exp: Experiment, out: Path) -> dict[str, Any]:
    """The 2 × 2 grid: trained on generated / artist poses × tested on the generated test split /
    the artist poses. A job's own evaluation covers its training source; the other is evaluated
    here once (`evaluation_on`, kept in the job's directory for the next report)."""
    grid: dict[str, dict[str, dict]] = {}
    for job in exp.done:
        trained = SOURCES.get(str(job.value("env.poses")), str(job.value("env.poses")))
        grid[trained] = {SOURCES[t]: evaluation_on(job, t)[POLICY] for t in SOURCES}
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.2))
    tests = list(SOURCES.values())
    for ax, metric in zip(axes, ("mje", "mroe")):
        for i, trained in enumerate(grid):
            means = [grid[trained][t][metric]["mean"] for t in tests]
            stds = [grid[trained][t][metric]["std"] for t in tests]
            ax.bar(np.arange(len(tests)) + (i - 0.5) * 0.38, means, 0.36, yerr=stds, capsize=4,
                   label=f"trained on {trained}")  # fmt: skip
        ax.set_xticks(np.arange(len(tests)), [f"tested on {t}" for t in tests])
        ax.set_ylabel(f"{metric.upper()} [rad]")
        ax.grid(axis="y", alpha=0.3)
        ax.legend()
    save_figure(fig, out, "Generated vs artist end poses (mean ± std)")

    rows = [[f"trained on {tr}"] + [f"{_ms(grid[tr][t]['mje'])} / {_ms(grid[tr][t]['mroe'])}" for t in tests]
            for tr in grid]  # fmt: skip
    both = {"generated", "artist"} <= set(grid)
    findings = [
        _finding(
            "training on generated poses tracks the artist poses about as well as training on them",
            grid["generated"]["artist"]["mje"]["mean"] <= 1.25 * grid["artist"]["artist"]["mje"]["mean"]
            if both else None,
            "MJE on artist poses, trained on generated / on artist: "
            + (f"{grid['generated']['artist']['mje']['mean']:.3f} / {grid['artist']['artist']['mje']['mean']:.3f}"
               if both else "n/a"),
        ),  # fmt: skip
        _finding(
            "training on artist poses generalises worse to generated poses than the reverse",
            grid["artist"]["generated"]["mje"]["mean"] > grid["generated"]["generated"]["mje"]["mean"]
            if both else None,
            "MJE on generated poses, trained on artist / on generated: "
            + (f"{grid['artist']['generated']['mje']['mean']:.3f} / {grid['generated']['generated']['mje']['mean']:.3f}"
               if both else "n/a"),
        ),  # fmt: skip
    ]
    md = _table(["", *(f"tested on {t}: MJE / MROE [rad]" for t in tests)], rows)
    return {"grid": grid, "markdown": md, "findings": findings}


# ---- 4. dataset size (fig:data_ablation) -----------------------------------------------------------------


def dataset_size(exp: Experiment, out: Path) -> dict[str, Any]:
    """MJE and MROE (mean ± std) against the fraction of the training split."""
    points = sorted((float(j.value("env.pose_fraction")), j.summary[POLICY]) for j in exp.done)
    frac = np.array([p[0] for p in points])
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.2))
    for ax, metric in zip(axes, ("mje", "mroe")):
        mean = np.array([p[1][metric]["mean"] for p in points])
        std = np.array([p[1][metric]["std"] for p in points])
        ax.errorbar(100 * frac, mean, yerr=std, fmt="-o", capsize=4, color=strategy_color(POLICY))
        ax.set_xscale("log")
        ax.set_xlabel("training poses [% of the training split]")
        ax.set_ylabel(f"{metric.upper()} [rad]")
        ax.grid(alpha=0.3)
    save_figure(fig, out, "Dataset size (mean ± std)")
    rows = [[f"{100 * f:g} %", _ms(s["mje"]), _ms(s["mroe"])] for f, s in points]
    enough = len(points) >= 2
    findings = [
        _finding(
            "more training poses lower the tracking errors (MJE and MROE)",
            bool(points[-1][1]["mje"]["mean"] < points[0][1]["mje"]["mean"]
                 and points[-1][1]["mroe"]["mean"] < points[0][1]["mroe"]["mean"]) if enough else None,
            "smallest → largest fraction: " + (
                f"MJE {points[0][1]['mje']['mean']:.3f} → {points[-1][1]['mje']['mean']:.3f}, "
                f"MROE {points[0][1]['mroe']['mean']:.3f} → {points[-1][1]['mroe']['mean']:.3f}" if enough else "n/a"),
        ),  # fmt: skip
    ]
    md = _table(["training poses", "MJE [rad]", "MROE [rad]"], rows)
    return {"points": [{"fraction": f, "mje": s["mje"], "mroe": s["mroe"]} for f, s in points], "markdown": md,
            "findings": findings}  # fmt: skip


# ---- 5. critical component (tab:impact_eval) --------------------------------------------------------------


def battery(exp: Experiment, out: Path) -> dict[str, Any]:
    """MJE, MROE (mean ± std) and the battery's max force (median, 95th percentile) per robot preset."""
    rows, table = [], {}
    for job in exp.done:
        robot, pol = str(job.value("robot.name")), job.summary[POLICY]
        force = pol["per_component"]["battery"]["max_impact_force"]
        weight = job.value("robot.sensitivity")["battery"]
        table[robot] = {"battery_weight": weight, "mje": pol["mje"], "mroe": pol["mroe"], "battery_max_force": force}
        rows.append([robot, f"{weight:g}", _ms(pol["mje"]), _ms(pol["mroe"]), f"{force['median']:.0f}",
                     f"{force['p95']:.0f}"])  # fmt: skip
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.2))
    names = list(table)
    x = np.arange(len(names))
    for i, q in enumerate(("median", "p95")):
        axes[0].bar(x + (i - 0.5) * 0.38, [table[n]["battery_max_force"][q] for n in names], 0.36, label=q)
    axes[0].set_ylabel("battery max force [N]")
    for i, m in enumerate(("mje", "mroe")):
        axes[1].bar(x + (i - 0.5) * 0.38, [table[n][m]["mean"] for n in names], 0.36,
                    yerr=[table[n][m]["std"] for n in names], capsize=4, label=m.upper())  # fmt: skip
    axes[1].set_ylabel("[rad]")
    for ax in axes:
        ax.set_xticks(x, [f"{n}\n(battery {table[n]['battery_weight']:g})" for n in names])
        ax.grid(axis="y", alpha=0.3)
        ax.legend()
    save_figure(fig, out, "Critical component: battery weighted 5 vs all weights 1")
    heavy = [n for n in names if table[n]["battery_weight"] > 1]
    base = [n for n in names if table[n]["battery_weight"] == 1]
    both = bool(heavy and base)
    h, b = (table[heavy[0]]["battery_max_force"], table[base[0]]["battery_max_force"]) if both else ({}, {})
    findings = [
        _finding(
            "weighting the battery lowers its max force (median and 95th percentile)",
            bool(h["median"] < b["median"] and h["p95"] < b["p95"]) if both else None,
            f"median {h['median']:.0f} vs {b['median']:.0f} N, p95 {h['p95']:.0f} vs {b['p95']:.0f} N" if both else "n/a",
        ),
        _finding(  # the paper: MJE 0.32 -> 0.42, MROE 0.11 -> 0.16 rad
            "protecting the battery costs some tracking (MJE and MROE rise)",
            bool(table[heavy[0]]["mje"]["mean"] > table[base[0]]["mje"]["mean"]
                 and table[heavy[0]]["mroe"]["mean"] > table[base[0]]["mroe"]["mean"]) if both else None,
            (f"MJE {table[heavy[0]]['mje']['mean']:.3f} vs {table[base[0]]['mje']['mean']:.3f}, MROE "
             f"{table[heavy[0]]['mroe']['mean']:.3f} vs {table[base[0]]['mroe']['mean']:.3f} rad") if both else "n/a",
        ),  # fmt: skip
    ]
    md = _table(["robot", "battery weight", "MJE [rad]", "MROE [rad]", "battery max force median [N]",
                 "p95 [N]"], rows)  # fmt: skip
    return {"table": table, "markdown": md, "findings": findings}


# ---- the report ----------------------------------------------------------------------------------------------

REPORTS: dict[str, tuple[str, Callable[[Experiment, Path], dict[str, Any]]]] = {
    "comparison": ("Comparison with the standard strategies (the paper's 'Impact Analysis' figure)", comparison),
    "impact_tracking": ("Impact vs tracking (the paper's 'Impact vs. Tracking Ablation' figure)", impact_tracking),
    "data_source": ("Generated vs artist training data (the paper's 'Sampling-Based End Pose Ablation' table)",
                    data_source),  # fmt: skip
    "dataset_size": ("Dataset size (the paper's 'Dataset Size' figure)", dataset_size),
    "battery": ("Critical component (the paper's 'Impact Reduction of Critical Components' table)", battery),
}


def write_report(sweep_dir: str | Path) -> Path:
    """Read the experiment directory, write its figure and tables; returns report.md's path."""
    exp = read_experiment(sweep_dir)
    if exp.name not in REPORTS:
        raise ConfigError(f"{exp.dir}: no report for experiment '{exp.name}'; known: {', '.join(REPORTS)}")
    title, make = REPORTS[exp.name]
    problems = exp.problems()
    for line in problems:
        log.warning("experiment %s: %s", exp.name, line)
    figure = exp.dir / f"{exp.name}.png"
    result = make(exp, figure) if exp.done else {"markdown": "(no finished runs: nothing to show)", "findings": []}
    status = f"{len(exp.done)} of {len(exp.jobs)} runs finished"
    md = [f"# {title}", "", f"Experiment directory: `{exp.dir}`. {status}."]
    if problems:
        md += ["", "Not in the figures:", *(f"- {p}" for p in problems)]
    md += ["", result["markdown"], ""]
    if exp.done:
        md += [f"![{exp.name}]({figure.name})", ""]
    if result["findings"]:
        md += ["The paper's findings, in direction:", ""]
        verdict = {True: "reproduced", False: "not reproduced", None: "no clear trend (or too few runs)"}
        md += [f"- {f['claim']}: **{verdict[f['reproduced']]}** ({f['figures']})" for f in result["findings"]]
    (exp.dir / "report.md").write_text("\n".join(md) + "\n")
    runs = [{"swept": j.swept, "status": j.status, "reason": j.reason, "dir": str(j.dir) if j.dir else None}
            for j in exp.jobs]  # fmt: skip
    body = {k: v for k, v in result.items() if k != "markdown"}
    (exp.dir / "report.json").write_text(json.dumps({"experiment": exp.name, "runs": runs, **body}, indent=2))
    print(f"experiment {exp.name}: {status}; report in {exp.dir / 'report.md'}")
    for line in problems:
        print(f"  {line}")
    return exp.dir / "report.md"


class ReportCallback(Callback):
    """Hydra callback of `experiment=<name>` sweeps: the report once every job has ended."""

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        write_report(config.hydra.sweep.dir)


__all__ = ["REPORTS", "ReportCallback", "write_report", "Job"]
