"""The Hydra application: `python -m fallkit [mode=…] [key=value …] [-m]`.

One app; `mode=` picks the verb (train by default), so every verb takes the
same overrides and `-m` sweeps. Robots registered by any installed plugin are
put into Hydra's ConfigStore as `robot/<name>` before composition, so no plugin
writes files into fallkit.
"""

from __future__ import annotations

import importlib
import logging
import re
import sys
from pathlib import Path
from typing import Any, Callable

import hydra
from hydra.core.config_store import ConfigStore
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from fallkit import registry
from fallkit.checkpoint import CheckpointError
from fallkit.config import ConfigError, FallkitConfig, validate
from fallkit.registry import PluginError
from fallkit.render import RenderError
from fallkit.robots.spec import RobotSpecError

log = logging.getLogger("fallkit")

# mode -> "module:function(config, run_dir)"; imported only when chosen
MODES: dict[str, str] = {
    "train": "fallkit.train:run_train",
    "export": "fallkit.export:run_export",
    "list": "fallkit.app:list_plugins",
    "eval": "fallkit.evaluate:run_eval",
    "render": "fallkit.render:run_render",
    "poses": "fallkit.samplers.end_poses:run_poses",
}

# Errors that are the user's to fix: one line, exit status 2, no traceback.
USER_ERRORS = (ConfigError, PluginError, RobotSpecError, CheckpointError, RenderError, FileNotFoundError)


def fail(message: str) -> None:
    print(f"fallkit: error: {message}", file=sys.stderr)
    sys.exit(2)


def register_robots() -> None:
    """One ConfigStore node per registered robot: its name and default sensitivity weights."""
    cs = ConfigStore.instance()
    for name in registry.names("fallkit.robots"):
        try:
            spec = registry.load("fallkit.robots", name)
            weights = {c: comp.weight for c, comp in spec.components.items()}
        except (PluginError, RobotSpecError):
            weights = {}  # selecting it reports the plugin's error
        cs.store(group="robot", name=name, node={"name": name, "sensitivity": weights})


def check_robot_overrides(argv: list[str]) -> None:
    """`robot=nosuch` is one clear line naming the robots that exist, before Hydra starts."""
    known = registry.names("fallkit.robots")
    for arg in argv:
        m = re.fullmatch(r"\+{0,2}robot=(.+)", arg)
        if not m or re.search(r"[(){}\[\]*$]", m.group(1)):
            continue  # sweep functions and interpolations are left to Hydra
        for name in m.group(1).split(","):
            if name not in known:
                fail(f"unknown robot '{name}'; registered robots: {', '.join(known) or 'none'}")


def run(cfg: DictConfig) -> Any:
    """The task: validate, save the resolved config, dispatch to the mode."""
    try:
        raw = OmegaConf.to_container(cfg, resolve=True)
        config = validate(raw)
        run_dir = Path(HydraConfig.get().runtime.output_dir)
        run_dir.mkdir(parents=True, exist_ok=True)
        (run_dir / "resolved_config.yaml").write_text(OmegaConf.to_yaml(raw))
        module, func = MODES[config.mode].split(":")
        handler: Callable[[FallkitConfig, Path], Any] = getattr(importlib.import_module(module), func)
        return handler(config, run_dir)
    except USER_ERRORS as exc:
        fail(str(exc))


@hydra.main(version_base="1.3", config_path="conf", config_name="config")
def _hydra_main(cfg: DictConfig) -> Any:
    return run(cfg)


def main() -> None:
    try:
        register_robots()
    except PluginError as exc:  # e.g. a robot name registered twice
        fail(str(exc))
    check_robot_overrides(sys.argv[1:])
    _hydra_main()


# ---- mode=list ----------------------------------------------------------------------


def list_plugins(config: FallkitConfig, run_dir: Path) -> None:
    """Print every registered robot, reward term and sampler with its distribution."""
    broken = 0
    for group in registry.GROUPS:
        print(f"{group}:")
        unique, duplicated = registry.scan(group)
        for name in sorted({*unique, *duplicated}):
            if name in duplicated:
                broken += 1
                where = ", ".join(e.distribution for e in duplicated[name])
                print(f"  {name:24s} ERROR: registered by several distributions ({where})")
                continue
            entry = unique[name]
            try:
                registry.load(group, name)
                status = ""
            except PluginError as exc:
                broken += 1
                status = f"  ERROR: {exc}"
            print(f"  {name:24s} {entry.distribution} ({entry.entry_point.value}){status}")
    if broken:
        print(f"{broken} plugin entr{'y' if broken == 1 else 'ies'} cannot be used (see ERROR above)", file=sys.stderr)
        sys.exit(1)
