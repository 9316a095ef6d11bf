"""Checkpoints: written atomically, read with a clear error when damaged.

A checkpoint is written to a temporary file in the same directory, flushed to
disk, then renamed over the target, so a run killed at any moment leaves either
the previous checkpoint or the new one — never half of one.
"""

from __future__ import annotations

import os
import pickle
import tempfile
import zipfile
from pathlib import Path
from typing import Any

import torch

from fallkit.errors import CheckpointError

FORMAT_VERSION = 1




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


def resolve_checkpoint(where: str | Path) -> Path:
    """A checkpoint file, or a run directory whose checkpoints/last.pt is taken."""
    p = Path(where).expanduser()
    if p.is_dir():
        p = p / "checkpoints" / "last.pt"
    if not p.is_file():
        raise CheckpointError(f"checkpoint not found: {p}")
    return p


def load_checkpoint(where: str | Path, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    path = resolve_checkpoint(where)
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
    return data


def _umask() -> int:
    """The process's file-creation mask (reading it means setting it; put back at once)."""
    mask = os.umask(0)
    os.umask(mask)
    return mask
