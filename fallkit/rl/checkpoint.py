"""Checkpoints: written atomically, read with a clear error when damaged.

A checkpoint is written to a temporary file in the same directory, flushed to
disk, then renamed over the target, so a run killed at any moment leaves either
the previous checkpoint or the new one — never half of one.

A run directory stands for its newest intact checkpoint: `last.pt` is written
when a run ends, so a run killed with `kill -9` has only `iter_*.pt`; the newest
of all of them that loads is taken (damaged ones are skipped, each with a warning).
"""

from __future__ import annotations

import logging
import os
import pickle
import tempfile
import zipfile
from pathlib import Path
from typing import Any

import torch

from fallkit.errors import CheckpointError

FORMAT_VERSION = 1

log = logging.getLogger(__name__)


def save_checkpoint(path: str | Path, payload: dict[str, Any]) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            torch.save({"format_version": FORMAT_VERSION, **payload}, f)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes it 0600: colleagues could not read the checkpoint
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def run_checkpoints(run_dir: Path) -> list[Path]:
    """A run's checkpoint files, newest first (by the time they were written)."""
    files = [*run_dir.glob("checkpoints/iter_*.pt"), *run_dir.glob("checkpoints/last.pt")]
    return sorted(files, key=lambda f: (f.stat().st_mtime_ns, f.name), reverse=True)


def load_checkpoint(where: str | Path, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """A checkpoint file, or the newest intact checkpoint of a run directory."""
    p = Path(where).expanduser()
    if not p.is_dir():
        if not p.is_file():
            raise CheckpointError(f"checkpoint not found: {p}")
        return _load(p, map_location)
    found = run_checkpoints(p)
    if not found:
        raise CheckpointError(
            f"no checkpoint in {p}/checkpoints: the run stopped before its first one (train.checkpoint_every)"
        )
    for i, path in enumerate(found):
        try:
            return _load(path, map_location)
        except CheckpointError as exc:
            if i == len(found) - 1:
                raise
            log.warning("skipped a damaged checkpoint: %s", exc)
    raise AssertionError("unreachable")


def _load(path: Path, map_location: str | torch.device) -> dict[str, Any]:
    try:
        data = torch.load(path, map_location=map_location, weights_only=False)
    except (EOFError, RuntimeError, pickle.UnpicklingError, zipfile.BadZipFile, OSError, ValueError) as exc:
        raise CheckpointError(
            f"checkpoint {path} is corrupt or truncated ({type(exc).__name__}: {str(exc).splitlines()[0][:200]}); "
            "resume from an earlier checkpoint in the same directory"
        ) from None
    if not isinstance(data, dict) or "format_version" not in data:
        raise CheckpointError(f"{path} is not a fallkit checkpoint")
    if data["format_version"] != FORMAT_VERSION:
        raise CheckpointError(
            f"checkpoint {path} has format version {data['format_version']}; this fallkit reads version {FORMAT_VERSION}"
        )
    data["path"] = str(path)
    _defaults_of_their_time(data.get("config"))
    return data


def _defaults_of_their_time(config: dict | None) -> None:
    """Settings a checkpoint's config lacks because it was saved before they existed take the value that
    reproduces how it was trained, not today's default (a policy must act as it learned to)."""
    if isinstance(config, dict) and isinstance(config.get("train"), dict):
        config["train"].setdefault("prior_power", 1.0)  # the default became 8 (docs/training.md)
        config["train"].setdefault("precision", "float32")  # train.precision came later
        if isinstance(config["train"].get("ppo"), dict):
            config["train"]["ppo"].setdefault("value_per_term", False)  # one value of the whole return before
            config["train"]["ppo"].setdefault("prior_coef", 0.0)  # no pull toward the prior before


def checkpoint_run_dir(path: str | Path) -> Path | None:
    """The run directory a checkpoint file belongs to (<run>/checkpoints/<file>), if it is in one."""
    path = Path(path)
    return path.parent.parent if path.parent.name == "checkpoints" else None


def _umask() -> int:
    """The process's file-creation mask (reading it means setting it; put back at once)."""
    mask = os.umask(0)
    os.umask(mask)
    return mask


def shape_mismatch(here: dict[str, torch.Tensor], there: dict[str, torch.Tensor]) -> str:
    """The first parameter whose presence or shape differs, in words ('' when they all match)."""
    for key in sorted(here.keys() | there.keys()):
        a, b = here.get(key), there.get(key)
        if a is None or b is None:
            return f"'{key}' exists only {'in the checkpoint' if a is None else 'in this run'}"
        if a.shape != b.shape:
            return f"'{key}' is {list(b.shape)} there and {list(a.shape)} here"
    return ""
