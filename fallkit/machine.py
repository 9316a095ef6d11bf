"""What fallkit knows about the machine it runs on: its cache folder and its share of the cores.

Sharing the cores. Two trainings that each size MuJoCo's and torch's thread pools to
every core do not share a 2-core machine, they collapse (benchmarks/parallel_runs.py,
docs/training.md): the PPO update, torch's OpenMP pool, went from 0.70 to 2.9 s per
iteration, because GNU OpenMP spin-waits at every barrier and with more threads than
cores a spinning thread holds the core its descheduled partner needs. MuJoCo's pool
sleeps while it waits, so collection only took its fair 1.7x. So every CPU-heavy
fallkit process (`running()`, entered by the app for train, eval, poses and render)
writes its pid into `<cache>/running/`, and sizes its pools to `core_share()`: the
usable cores divided by the fallkit processes alive now (at least one). The trainer
asks again every iteration, so a run that started alone gives back cores when a
second one starts. Explicit `sim.threads` / `train.torch_threads` always win. The
folder is per user (the cache folder): other users' processes are not seen.

Subnormal floats. x86 computes with subnormal floats (|x| < 1.2e-38) an order of magnitude
slower, and a trained critic makes many: its later layers take inputs far below zero, whose
ELU goes through exp(x) < 1e-38. Unflushed, biped20's update slowed from 0.28 s per iteration
to 0.36 s by iteration 1200 and 0.39 s by 4000 (docs/learning_log.md); the trainer's update runs
in `subnormals_flushed()` and stays at 0.28 s. Only torch's threads flush: MuJoCo's physics
and its threads keep IEEE arithmetic.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import os
from collections.abc import Iterator
from pathlib import Path

log = logging.getLogger(__name__)


def cache_root(cache_dir: str | Path | None = None) -> Path:
    """fallkit's cache: `cache_dir`, else $FALLKIT_CACHE_DIR, else $XDG_CACHE_HOME/fallkit, else ~/.cache/fallkit."""
    if cache_dir is not None:
        return Path(cache_dir)
    if os.environ.get("FALLKIT_CACHE_DIR"):
        return Path(os.environ["FALLKIT_CACHE_DIR"])
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "fallkit"


def usable_cores() -> int:
    """Cores this process may run on (its affinity mask: taskset, cgroup cpusets)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def _running_dir() -> Path:
    return cache_root() / "running"


def _start_time(pid: int) -> str:
    """The process's start time (/proc), so that a reused pid is not taken for a running fallkit."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[19]
    except (OSError, IndexError):
        return ""


def _alive(entry: Path) -> bool:
    try:
        pid = int(entry.stem)
        os.kill(pid, 0)
    except (ValueError, ProcessLookupError):
        return False
    except PermissionError:  # alive, another user's
        return True
    try:
        return entry.read_text().strip() == _start_time(pid)
    except OSError:
        return False


def running_processes() -> int:
    """fallkit processes registered and alive now (stale entries of killed ones are removed)."""
    folder = _running_dir()
    if not folder.is_dir():
        return 0
    alive = 0
    for entry in folder.glob("*.pid"):
        if _alive(entry):
            alive += 1
        else:
            entry.unlink(missing_ok=True)
    return alive


def core_share() -> int:
    """This process's share of the cores: usable cores over the fallkit processes alive (>= 1)."""
    return max(1, usable_cores() // max(1, running_processes()))


@contextlib.contextmanager
def running() -> Iterator[None]:
    """Register this process as a CPU-heavy fallkit process for the duration of the block."""
    entry = _running_dir() / f"{os.getpid()}.pid"
    try:
        entry.parent.mkdir(parents=True, exist_ok=True)
        entry.write_text(_start_time(os.getpid()))
    except OSError:  # a read-only cache: this process just does not count for others
        entry = None
    try:
        yield
    finally:
        if entry is not None:
            entry.unlink(missing_ok=True)


@contextlib.contextmanager
def subnormals_flushed() -> Iterator[None]:
    """Subnormal floats flushed to zero in the block, where the CPU has such a mode.

    The mode (x86's MXCSR) is per thread and a new thread takes its creator's: torch's OpenMP
    threads flush when they are started inside this block — the trainer's first update starts
    them — and not when an earlier torch call started them, which is logged once. The calling
    thread gets its IEEE arithmetic back after the block; torch's threads keep flushing.
    """
    import torch

    if not torch.set_flush_denormal(True):
        yield
        return
    try:
        _check_torch_threads_flush()
        yield
    finally:
        torch.set_flush_denormal(False)


@functools.cache  # once per process: a thread keeps its mode
def _check_torch_threads_flush() -> None:
    import torch

    # the smallest subnormal float32, made from its bits (a float written here would be flushed here):
    # a product stays non-zero only in a thread that does not flush; 2^16 elements are split over
    # the threads (torch's grain is 2^15), starting them if need be. Its bits are read as numpy: host memory,
    # not a device read, and integers, which the flushing calling thread cannot take for zero.
    smallest = torch.ones(1 << 16, dtype=torch.int32).view(torch.float32)
    if smallest.mul_(1.0).view(torch.int32).numpy().any():
        log.warning(
            "torch's threads were started before this block and do not flush subnormal floats: "
            "a trained critic's update may run slower (fallkit.machine.subnormals_flushed)"
        )
