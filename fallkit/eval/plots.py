"""Plots of an evaluation a person looks at (matplotlib, no display needed).

- impact_boxplot.png     max / mean / fall-phase mean impact per strategy (the paper's Fig. 5)
- component_impact.png   per-component max impact force: median and 95th percentile bars
- tracking_boxplot.png   MROE and MJE per strategy
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # headless; before pyplot is imported anywhere
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from fallkit.eval.metrics import TrialMetrics  # noqa: E402

# One colour per strategy, the same in every figure.
COLORS = {"policy": "#2a7ab0", "zero_torque": "#8c8c8c", "damping": "#e0a030", "freeze": "#c0392b"}


def strategy_color(name: str) -> str:
    return COLORS.get(name, "#6a3d9a")


def boxplot(ax, data: list[np.ndarray], names: list[str], ylabel: str, title: str) -> None:
    box = ax.boxplot(data, showfliers=True, patch_artist=True, widths=0.6, flierprops={"markersize": 2, "alpha": 0.4})
    for patch, name in zip(box["boxes"], names):
        patch.set_facecolor(strategy_color(name))
        patch.set_alpha(0.75)
    for median in box["medians"]:
        median.set_color("black")
    ax.set_xticks(range(1, len(names) + 1), [n.replace("_", " ") for n in names])
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(axis="y", alpha=0.3)


def save_figure(fig, path: Path, title: str) -> Path:
    """Title, layout, PNG at 110 dpi, and close: the ending of every figure here."""
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def impact_boxplot(results: dict[str, TrialMetrics], path: Path, title: str = "") -> Path:
    """Box plots of max, mean and fall-phase mean impact force per strategy."""
    names = list(results)
    fig, axes = plt.subplots(1, 3, figsize=(13, 4.2))
    panels = [
        ("max_impact_force", "max impact force"),
        ("mean_impact_force", "mean impact force"),
        ("fall_mean_impact_force", "mean impact force, fall phase"),
    ]
    for ax, (key, label) in zip(axes, panels):
        boxplot(ax, [getattr(results[n], key) for n in names], names, "force [N]", label)
    return save_figure(fig, path, title)


def tracking_boxplot(results: dict[str, TrialMetrics], path: Path, title: str = "") -> Path:
    """Box plots of the root orientation error (MROE) and joint error (MJE) per strategy."""
    names = list(results)
    fig, axes = plt.subplots(1, 2, figsize=(9, 4.2))
    boxplot(axes[0], [results[n].mroe for n in names], names, "[rad]", "root orientation error (MROE)")
    boxplot(axes[1], [results[n].mje for n in names], names, "[rad]", "joint error (MJE)")
    return save_figure(fig, path, title)


def component_impact(results: dict[str, TrialMetrics], components: list[str], path: Path, title: str = "") -> Path:
    """Grouped bars per component: median and 95th percentile of the per-trial max force."""
    names = list(results)
    x = np.arange(len(components))
    width = 0.8 / len(names)
    fig, axes = plt.subplots(1, 2, figsize=(13, 4.2), sharey=False)
    for ax, (q, label) in zip(axes, [(50, "median"), (95, "95th percentile")]):
        for i, n in enumerate(names):
            v = np.percentile(results[n].component_max_force, q, axis=0)
            ax.bar(x + (i - (len(names) - 1) / 2) * width, v, width, label=n.replace("_", " "), color=strategy_color(n))
        ax.set_xticks(x, components)
        ax.set_ylabel("max impact force [N]")
        ax.set_title(f"per component: {label} over trials")
        ax.grid(axis="y", alpha=0.3)
    axes[0].legend(fontsize=8)
    return save_figure(fig, path, title)


def plot_all(results: dict[str, TrialMetrics], components: list[str], out_dir: Path, title: str = "") -> list[Path]:
    """Every evaluation figure into `out_dir`; returns the written paths."""
    out_dir = Path(out_dir)
    return [
        impact_boxplot(results, out_dir / "impact_boxplot.png", title),
        component_impact(results, components, out_dir / "component_impact.png", title),
        tracking_boxplot(results, out_dir / "tracking_boxplot.png", title),
    ]


def moving_average(y: np.ndarray, k: int) -> np.ndarray:
    """Centred mean over k points, gaps (NaN) filled by interpolation. Near the ends it averages over
    the points there are: padding with zeros would bend every curve toward 0 in its first and last k/2
    iterations, and a run's last iterations are the ones a reader looks at."""
    ok = np.isfinite(y)
    if ok.sum() < 2:
        return y
    y = np.interp(np.arange(len(y)), np.flatnonzero(ok), y[ok])
    if k <= 1:
        return y
    window = np.ones(k)
    return np.convolve(y, window, mode="same") / np.convolve(np.ones_like(y), window, mode="same")


def learning_curve(metrics_csv: Path, path: Path, title: str = "") -> Path:
    """Training progress from metrics.csv: reward, episode impact and the reward terms per iteration."""
    import csv

    with open(metrics_csv, newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows:
        raise ValueError(f"{metrics_csv} has no iterations")
    it = np.array([float(r["iteration"]) for r in rows])

    def column(key: str) -> np.ndarray:
        return np.array([float(r[key]) if r.get(key) not in (None, "") else np.nan for r in rows])

    def smooth(y: np.ndarray) -> np.ndarray:
        return moving_average(y, max(1, len(rows) // 50))

    fig, axes = plt.subplots(1, 3, figsize=(15, 4))
    axes[0].plot(it, smooth(column("reward")))
    axes[0].set(xlabel="iteration", ylabel="mean reward per step", title="reward")
    axes[1].plot(it, smooth(column("episode/max_impact_force")), color="tab:red")
    axes[1].set(xlabel="iteration", ylabel="max impact force per episode [N]", title="impact (with exploration noise)")
    for key in rows[0]:
        if key.startswith("reward_terms/"):
            axes[2].plot(it, smooth(column(key)), label=key.split("/", 1)[1])
    axes[2].set(xlabel="iteration", ylabel="weight · term · dt per step", title="reward terms")
    axes[2].legend(fontsize=7, ncol=2)
    for ax in axes:
        ax.grid(alpha=0.3)
    return save_figure(fig, path, title)
