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
from fallkit.config import FallkitConfig, defaults, validate
from fallkit.errors import FallkitError, PluginError
from fallkit.robots import GROUP as ROBOTS
from fallkit.robots import get_robot

log = logging.getLogger("fallkit")

# mode -> "module:function(config, run_dir)"; imported only when chosen, so `mode=list`
# does not pay for TorchRL and MuJoCo's renderer
MODES: dict[str, str] = {
    "train": "fallkit.app:train",
    "export": "fallkit.rl.export:run_export",
    "list": "fallkit.app:list_plugins",
    "eval": "fallkit.eval.evaluate:run_eval",
    "render": "fallkit.eval.render:run_render",
    "poses": "fallkit.eval.dataset_report:run_poses",
}


def fail(message: str) -> None:
    print(f"fallkit: error: {message}", file=sys.stderr)
    sys.exit(2)


def register_configs() -> None:
    """Fill Hydra's ConfigStore: every default (`fallkit_defaults`, from the pydantic models)
    and one `robot/<name>` node per registered robot with its default sensitivity weights."""
    cs = ConfigStore.instance()
    cs.store(name="fallkit_defaults", node=defaults())
    for name in registry.names(ROBOTS):
        try:
            spec = get_robot(name)
            weights = {c: comp.weight for c, comp in spec.components.items()}
        except FallkitError:
            weights = {}  # selecting it reports the plugin's error
        cs.store(group="robot", name=name, node={"name": name, "sensitivity": weights})


def check_robot_overrides(argv: list[str]) -> None:
    """`robot=nosuch` is one clear line naming the robots that exist, before Hydra starts."""
    known = registry.names(ROBOTS)
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
    except FallkitError as exc:
        fail(str(exc))


@hydra.main(version_base="1.3", config_path="conf", config_name="config")
def _hydra_main(cfg: DictConfig) -> Any:
    return run(cfg)


def main() -> None:
    try:
        register_configs()
    except PluginError as exc:  # e.g. a robot name registered twice
        fail(str(exc))
    check_robot_overrides(sys.argv[1:])
    _hydra_main()


# ---- mode=train ----------------------------------------------------------------------


def train(config: FallkitConfig, run_dir: Path) -> Path:
    """`mode=train`: PPO (fallkit.rl.trainer), its learning curve, then the final policy
    against the standard strategies on falls it never trained on."""
    from fallkit.eval.evaluate import evaluate_checkpoint
    from fallkit.eval.plots import learning_curve
    from fallkit.rl.trainer import Trainer

    trainer = Trainer(config, run_dir)
    last = trainer.run()
    if not trainer.main_rank:
        return last
    if trainer.iteration > trainer.start:
        title = f"{trainer.spec.name}: training"
        print(f"learning curve: {learning_curve(run_dir / 'metrics.csv', run_dir / 'learning_curve.png', title)}")
    if config.train.evaluate and not trainer.stopped:
        evaluate_checkpoint(config, run_dir, last)
    return last


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
                get_robot(name) if group == ROBOTS else registry.load(group, name)
                status = ""
            except PluginError as exc:
                broken += 1
                status = f"  ERROR: {exc}"
            print(f"  {name:24s} {entry.distribution} ({entry.entry_point.value}){status}")
    if broken:
        print(f"{broken} plugin entr{'y' if broken == 1 else 'ies'} cannot be used (see ERROR above)", file=sys.stderr)
        sys.exit(1)
