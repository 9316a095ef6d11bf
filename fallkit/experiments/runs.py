"""The runs of one experiment directory: which jobs the sweep asked for, which finished, which failed.

An experiment directory is a Hydra multirun's sweep directory (`experiments/<name>/<time>`):
`multirun.yaml` holds the composed sweep (the experiment's `hydra.sweeper.params` and the
command line), and each job has a subdirectory with `.hydra/overrides.yaml`,
`resolved_config.yaml` and, once its training and evaluation finished, `eval.json`.
The expected jobs are expanded from the sweep exactly as Hydra's basic sweeper does
(command-line sweeps replace the experiment's for the same key), so a job that never
started is named as missing even though it has no directory.
"""

from __future__ import annotations

import itertools
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import yaml
from hydra.core.override_parser.overrides_parser import OverridesParser

from fallkit.errors import ConfigError

Status = Literal["done", "failed", "missing"]


@dataclass
class Job:
    """One job of the sweep: its swept values and what its run directory holds."""

    swept: dict[str, str]  # swept key -> value, as on the command line ({"reward.impact": "50"})
    status: Status
    reason: str = ""  # why it is failed or missing
    dir: Path | None = None
    config: dict[str, Any] = field(default_factory=dict)  # resolved_config.yaml
    summary: dict[str, Any] = field(default_factory=dict)  # eval.json

    @property
    def label(self) -> str:
        return ", ".join(f"{k}={v}" for k, v in self.swept.items()) or "(single run)"

    def value(self, dotted: str) -> Any:
        """A value of the job's resolved config, e.g. value("reward.impact")."""
        node: Any = self.config
        for part in dotted.split("."):
            node = node[part]
        return node

    def trials(self) -> dict[str, np.ndarray]:
        """eval_trials.npz: every per-trial figure of every strategy ("<strategy>/<figure>")."""
        with np.load(self.dir / "eval_trials.npz") as z:
            return {k: z[k] for k in z.files}


@dataclass
class Experiment:
    """An experiment directory, read."""

    name: str
    dir: Path
    jobs: list[Job]

    @property
    def done(self) -> list[Job]:
        return [j for j in self.jobs if j.status == "done"]

    def problems(self) -> list[str]:
        """One plain line per job that is not done."""
        return [f"{j.status}: {j.label}: {j.reason}" for j in self.jobs if j.status != "done"]


def read_experiment(sweep_dir: str | Path) -> Experiment:
    """Read an experiment directory; a directory that is not one is a ConfigError naming the fix."""
    root = Path(sweep_dir)
    multirun = root / "multirun.yaml"
    if not multirun.is_file():
        raise ConfigError(
            f"{root}: not an experiment directory (no multirun.yaml); give the directory "
            "`python -m fallkit -m experiment=<name>` printed (experiments/<name>/<time>)"
        )
    composed = yaml.safe_load(multirun.read_text())
    name = composed.get("experiment")
    if not name:
        raise ConfigError(f"{root}: this sweep was not run with experiment=<name>, so it has no report")
    expected = _expected_jobs(composed["hydra"])
    found = {_job_key(d, list(expected[0])): d for d in _job_dirs(root)} if expected else {}
    jobs = [_read_job(dict(swept), found.get(tuple(swept.items()))) for swept in expected]
    return Experiment(name=name, dir=root, jobs=jobs)


def _expected_jobs(hydra: dict[str, Any]) -> list[dict[str, str]]:
    """Every job of the sweep as {key: value}, in Hydra's order (the basic sweeper's product)."""
    params = [f"{k}={v}" for k, v in (hydra.get("sweeper", {}).get("params") or {}).items()]
    task = hydra.get("overrides", {}).get("task", [])
    parser = OverridesParser.create()
    by_key: dict[str, list[str]] = {}
    for o in parser.parse_overrides(params):  # the experiment's parameters, single values included
        by_key[o.get_key_element()] = _values(o)
    for o in parser.parse_overrides(task):  # the command line's sweeps, and its values for those keys, win
        if o.is_sweep_override() or o.get_key_element() in by_key:
            by_key[o.get_key_element()] = _values(o)
    keys = list(by_key)
    return [dict(zip(keys, values)) for values in itertools.product(*by_key.values())]


def _values(o: Any) -> list[str]:
    return list(o.sweep_string_iterator()) if o.is_sweep_override() else [o.get_value_element_as_str()]


def _job_dirs(root: Path) -> list[Path]:
    return sorted(d for d in root.iterdir() if (d / ".hydra" / "overrides.yaml").is_file())


def _job_key(job_dir: Path, keys: list[str]) -> tuple[tuple[str, str], ...]:
    """The swept values a job ran with, from its own overrides.yaml."""
    values = {}
    for line in yaml.safe_load((job_dir / ".hydra" / "overrides.yaml").read_text()) or []:
        key, _, value = str(line).lstrip("+~").partition("=")
        values[key] = value
    return tuple((k, values.get(k, "")) for k in keys)


def _read_job(swept: dict[str, str], job_dir: Path | None) -> Job:
    if job_dir is None:
        return Job(swept, "missing", "no run directory: the job never started (re-run the sweep for it)")
    config_file, eval_file = job_dir / "resolved_config.yaml", job_dir / "eval.json"
    config = yaml.safe_load(config_file.read_text()) if config_file.is_file() else {}
    if not eval_file.is_file():
        ckpts = sorted((job_dir / "checkpoints").glob("*.pt")) if (job_dir / "checkpoints").is_dir() else []
        where = f"its newest checkpoint is {ckpts[-1].name}" if ckpts else "it wrote no checkpoint"
        return Job(
            swept, "failed", f"{job_dir.name} has no eval.json ({where}; its log is in {job_dir})", job_dir, config
        )
    try:
        summary = json.loads(eval_file.read_text())
    except json.JSONDecodeError as exc:
        return Job(swept, "failed", f"{eval_file} is damaged ({exc.msg}); run mode=eval on the job again", job_dir)
    return Job(swept, "done", "", job_dir, config, summary)
