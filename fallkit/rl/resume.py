"""Resuming a run: the run's own configuration, with what the command line changed on top.

`python -m fallkit resume=<run dir>` continues that run: its checkpoint holds the
configuration it was trained with (network sizes, presets, number of envs), so
the user need not repeat `train=quick` or any other override. Keys the command
line sets still win (`train.iterations=2000` to train further), and each one that
differs from the run's own value is named, so nothing changes unnoticed. A
checkpoint of another robot is refused before anything else is compared.
"""

from __future__ import annotations

import copy
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

from fallkit.config import ConfigError, FallkitConfig, validate
from fallkit.errors import CheckpointError
from fallkit.rl.checkpoint import load_checkpoint

_ALWAYS_FROM_COMMAND_LINE = ("mode", "resume", "checkpoint")


@dataclass
class Resumed:
    """The configuration to continue with, and what the command line changed in it."""

    config: FallkitConfig
    checkpoint: str  # the checkpoint file taken
    iteration: int
    changed: list[str]  # "key: run's value -> command line's value"


def leaves(tree: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """{dotted key: value} of every leaf of a nested dict (lists are leaves)."""
    out: dict[str, Any] = {}
    for k, v in tree.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict) and v:
            out.update(leaves(v, key + "."))
        else:
            out[key] = v
    return out


def resume_config(config: FallkitConfig, set_by_command_line: Iterable[str]) -> Resumed:
    """`config` (composed from the command line) with every key the command line did not set taken
    from the configuration the checkpoint of `config.resume` was trained with."""
    ckpt = load_checkpoint(config.resume)
    saved: dict[str, Any] = ckpt["config"]
    current = config.model_dump(mode="json")
    touched = {k for k in leaves(current) if any(k == s or k.startswith(s + ".") for s in set_by_command_line)}
    if any(k.startswith("robot.") for k in touched) and current["robot"]["name"] != saved["robot"]["name"]:
        raise CheckpointError(
            f"resume: {ckpt['path']} was trained on robot '{saved['robot']['name']}', but this run asks for robot "
            f"'{current['robot']['name']}': drop robot= to continue that run, or drop resume= to start a new one"
        )
    merged = copy.deepcopy(saved)
    now, before = leaves(current), leaves(saved)
    changed = []
    for key in sorted(touched | {k for k in now if k.split(".")[0] in _ALWAYS_FROM_COMMAND_LINE}):
        _set(merged, key, now[key])
        if key.split(".")[0] not in _ALWAYS_FROM_COMMAND_LINE and before.get(key) != now[key]:
            changed.append(f"{key}: {before.get(key)!r} -> {now[key]!r}")
    merged["resume"] = ckpt["path"]  # the file taken, not the run directory: what resolved_config.yaml records
    try:
        resumed = validate(merged)
    except ConfigError as exc:
        raise ConfigError(f"resume: the configuration of {ckpt['path']} with this command line: {exc}") from None
    return Resumed(resumed, ckpt["path"], int(ckpt["iteration"]), changed)


def _set(tree: dict[str, Any], key: str, value: Any) -> None:
    *parents, leaf = key.split(".")
    for p in parents:
        tree = tree.setdefault(p, {})
    tree[leaf] = value
