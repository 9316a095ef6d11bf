"""What a training run shows and keeps while it runs: the progress bar, TensorBoard and
metrics.csv, the finished episodes' impacts, and a stop flag for SIGINT/SIGTERM (finish the
iteration, save, stop); and `host_reads`, the count that says how often the loop waits for the device."""

from __future__ import annotations

import collections
import csv
import math
import signal
import time
from pathlib import Path

import torch
from tensordict import TensorDict
from torchrl.envs import EnvBase
from tqdm import tqdm

# The aten operations by which the host reads a device value (`.item()`, `bool(tensor)`, a mask's
# `nonzero`, a tensor used as a size): on a GPU each waits for the launch queue to drain.
HOST_READ_OPS = ("aten::_local_scalar_dense", "aten::nonzero", "aten::item", "aten::is_nonzero")


def top_level_ops(prof) -> collections.Counter[str]:
    """The aten operations a torch profiler saw called from Python (an op's own sub-ops run inside its
    kernel on a GPU), by name: the CPU proxy for kernel launches (issue 15)."""
    counts: collections.Counter[str] = collections.Counter()
    for event in prof.events():
        if event.name.startswith("aten::") and (event.cpu_parent is None or not event.cpu_parent.name.startswith("aten::")):
            counts[event.name] += 1
    return counts


def host_reads(prof) -> int:
    """How many of a profile's top-level operations read a device value back to the host."""
    counts = top_level_ops(prof)
    return sum(counts[name] for name in HOST_READ_OPS)


class StopFlag:
    """SIGINT/SIGTERM ask the loop to stop after the current iteration (and save); a second one stops at once."""

    def __init__(self):
        self.requested: str | None = None
        self._previous = {}
        for sig in (signal.SIGINT, signal.SIGTERM):
            try:
                self._previous[sig] = signal.signal(sig, self._handle)
            except ValueError:  # not the main thread
                pass

    def _handle(self, signum, frame) -> None:
        if self.requested:
            raise KeyboardInterrupt
        self.requested = signal.Signals(signum).name

    def restore(self) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)


def _whole(value: float) -> str:
    """A figure for the bar; "-" while there is none (no episode has ended yet in the first iterations)."""
    return f"{value:.0f}" if math.isfinite(value) else "-"


class Progress:
    """The training bar: iterations, speed, reward, impact and learning rate; time left under a budget."""

    def __init__(self, total: int, start: int, max_minutes: float | None, enabled: bool):
        self.started = time.monotonic()
        self.budget_s = None if max_minutes is None else 60.0 * max_minutes
        # a time budget ends the run long before the iteration budget: show the time left, not a share of iterations
        bar_format = "{desc}: {n_fmt} it [{elapsed}, {rate_fmt}{postfix}]" if self.budget_s else None
        self.bar = tqdm(
            total=total, initial=start, desc="train", unit="it", disable=not enabled, dynamic_ncols=True,
            bar_format=bar_format,
        )  # fmt: skip

    @property
    def elapsed(self) -> float:
        return time.monotonic() - self.started

    @property
    def spent(self) -> float:
        """The share of the run's budget gone: of its iterations or of its minutes, whichever ends it first."""
        share = self.bar.n / self.bar.total if self.bar.total else 0.0
        return min(1.0, max(share, self.elapsed / self.budget_s if self.budget_s else 0.0))

    @property
    def out_of_time(self) -> bool:
        return self.budget_s is not None and self.elapsed > self.budget_s

    def update(self, stats: dict[str, float]) -> None:
        left = {} if self.budget_s is None else {"left": tqdm.format_interval(max(0, self.budget_s - self.elapsed))}
        self.bar.set_postfix(
            steps_s=f"{stats['env_steps_per_s']:.0f}",
            reward=f"{stats['reward']:.3f}",
            impact_N=_whole(stats.get("episode/max_impact_force", float("nan"))),
            lr=f"{stats['learning_rate_mean']:.1e}",  # what the steps were taken at; the last one's can sit at lr_min
            **left,
            refresh=False,
        )
        self.bar.update(1)

    def close(self) -> None:
        self.bar.close()


class MetricsLog:
    """TensorBoard scalars and a CSV of the same figures, one row per iteration (main rank only)."""

    def __init__(self, run_dir: Path, enabled: bool, start: int = 0, resumed_from: Path | None = None):
        """A resumed run (`start` > 0) keeps the rows up to `start` of the run it continues
        (`resumed_from`, possibly this same directory) and drops the later ones: those
        iterations are trained again, and a curve must not hold them twice."""
        self.enabled = enabled
        if not enabled:
            return
        from torch.utils.tensorboard import SummaryWriter  # imports TensorBoard: only where logging happens

        # purge_step hides the events at and after it that a killed run had already written
        self.tb = SummaryWriter(str(run_dir / "tensorboard"), purge_step=start + 1 if start else None)
        self.csv_path = run_dir / "metrics.csv"
        if start:
            _keep_rows_up_to(self.csv_path, start, (resumed_from or run_dir) / "metrics.csv")
        self._file = None
        self._writer = None
        self._fields: list[str] | None = None

    def log(self, it: int, stats: dict[str, float]) -> None:
        if not self.enabled:
            return
        for k, v in stats.items():
            self.tb.add_scalar(k, v, it)
        row = {"iteration": it, **stats}
        if self._writer is None:
            new = not self.csv_path.exists() or self.csv_path.stat().st_size == 0
            header: list[str] = []
            if not new:
                with open(self.csv_path, newline="") as f:
                    header = next(csv.reader(f), [])
            self._file = open(self.csv_path, "a", newline="")
            self._fields = header or list(row)  # a continued file keeps its columns
            self._writer = csv.DictWriter(self._file, fieldnames=self._fields, extrasaction="ignore")
            if new:
                self._writer.writeheader()
        self._writer.writerow({k: row.get(k, "") for k in self._fields})
        self._file.flush()

    def close(self) -> None:
        if self.enabled:
            self.tb.close()
            if self._file:
                self._file.close()


def _keep_rows_up_to(path: Path, iteration: int, source: Path) -> None:
    """Write to `path` the header and the rows of `source` with iteration <= `iteration`
    (`source` may be `path` itself: then it is truncated in place, atomically)."""
    if not source.is_file():
        return
    with open(source, newline="") as f:
        rows = list(csv.reader(f))
    if not rows:
        return
    kept = [rows[0]] + [r for r in rows[1:] if r and r[0].isdigit() and int(r[0]) <= iteration]
    tmp = path.with_suffix(".csv.tmp")
    with open(tmp, "w", newline="") as f:
        csv.writer(f).writerows(kept)
    tmp.replace(path)


class EpisodeImpacts:
    """The worst contact force on any component over each finished episode, summed and counted on the
    device (no host read per step): `pop` gives their mean and count since the last call."""

    def __init__(self, env: EnvBase):
        self.running = torch.zeros(env.batch_size, device=env.device)
        self.total = torch.zeros((), device=env.device)
        self.count = torch.zeros((), device=env.device)

    def add(self, batch: TensorDict) -> None:
        force = batch["next", "contact_force"].amax(dim=-1)  # [N, T]
        done = batch["next", "done"].squeeze(-1)
        for t in range(force.shape[1]):
            self.running = torch.maximum(self.running, force[:, t])
            self.total += torch.where(done[:, t], self.running, 0.0).sum()
            self.count += done[:, t].sum()
            self.running = torch.where(done[:, t], 0.0, self.running)

    def pop(self) -> dict[str, torch.Tensor]:
        mean = self.total / self.count  # NaN when no episode finished
        stats = {"episode/max_impact_force": mean, "episode/count": self.count.clone()}
        self.total.zero_()
        self.count.zero_()
        return stats
