"""The Hydra application: `python -m fallkit [mode=…] [key=value …] [-m]`.

One app; `mode=` picks the verb (train by default), so every verb takes the
same overrides and `-m` sweeps. Robots registered by any installed plugin are
put into Hydra's ConfigStore as `robot/<name>` before composition, so no plugin
writes files into fallkit.
"""

from __future__ import annotations

import contextlib
import difflib
import importlib
import io
import logging
import re
import sys
from pathlib import Path
from typing import Any, Callable

import hydra
from hydra import compose, initialize_config_module
from hydra._internal.utils import get_args_parser  # Hydra's own command line: the same parse as @hydra.main
from hydra.core.config_store import ConfigStore
from hydra.core.global_hydra import GlobalHydra
from hydra.core.hydra_config import HydraConfig
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.errors import HydraException, MissingConfigException, OverrideParseException
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

from fallkit import registry
from fallkit.config import FallkitConfig, defaults, validate
from fallkit.errors import ConfigError, FallkitError, PluginError
from fallkit.machine import running
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
    "sim2sim": "fallkit.deploy.sim2sim:run_sim2sim",
    "detect": "fallkit.deploy.fall_detection:run_detect",
    "warmup": "fallkit.env.warmup:run_warmup",
    "play": "fallkit.play.server:run_play",
}


# modes that fill the cores: they register, and size their thread pools to their share (fallkit.machine)
CPU_HEAVY = ("train", "eval", "poses", "render", "sim2sim")


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


# ---- Hydra's composition errors in fallkit's one-line form -------------------------------------------


def check_overrides(argv: list[str]) -> None:
    """Compose every job of the command line before Hydra starts, so that an unknown key, group
    option or malformed override is one line naming the fix with exit 2 (Hydra prints several
    lines and exits 1). Commands Hydra handles itself (--help, --info, other configs) are left to it."""
    with contextlib.redirect_stderr(io.StringIO()):
        try:
            args = get_args_parser().parse_args(argv)
        except SystemExit:
            return  # Hydra reports its own usage errors
    if args.help or args.hydra_help or args.info or args.shell_completion or args.experimental_rerun:
        return
    if args.config_name or args.config_path or args.config_dir:
        return
    for overrides in _jobs(args.overrides, args.multirun):
        try:
            _compose(overrides, hydra_config=True)
        except HydraException as exc:
            fail(describe_override_error(exc))
        finally:
            GlobalHydra.instance().clear()


def composed_config(*overrides: str) -> FallkitConfig:
    """The validated FallkitConfig that `python -m fallkit <overrides>` runs with, without running it
    (benchmarks, tests and notebooks compose a run's config this way). A bad override is a ConfigError
    in the command line's words (`describe_override_error`), not Hydra's traceback."""
    register_configs()
    try:
        raw = OmegaConf.to_container(_compose(list(overrides)), resolve=False)
    except HydraException as exc:
        raise ConfigError(describe_override_error(exc)) from None
    raw.pop("hydra", None)
    return validate(raw)


def _compose(overrides: list[str], hydra_config: bool = False) -> DictConfig:
    GlobalHydra.instance().clear()
    with initialize_config_module(config_module="fallkit.conf", version_base="1.3"):
        return compose(config_name="config", overrides=overrides, return_hydra_config=hydra_config)


def _jobs(overrides: list[str], multirun: bool) -> list[list[str]]:
    """The override lists to check: each value of each sweep once, the other sweeps at their first value."""
    if not multirun:
        return [overrides]
    try:
        parsed = OverridesParser.create().parse_overrides(overrides)
    except OverrideParseException:
        return [overrides]  # composing reports it
    choices: list[list[str]] = []
    for o in parsed:
        if not o.is_sweep_override():
            choices.append([o.input_line])
            continue
        try:
            choices.append([f"{o.get_key_element()}={v}" for v in o.sweep_string_iterator()])
        except HydraException:  # glob() sweeps need the config loader: left to Hydra
            choices.append([])
    base = [c[0] for c in choices if c]
    jobs = [base]
    for i, c in enumerate(choices):
        for value in c[1:]:
            jobs.append([value if j == i else x[0] for j, x in enumerate(choices) if x])
    return jobs


def describe_override_error(exc: HydraException) -> str:
    """One line for a Hydra composition error: what is wrong and what to type instead."""
    text = str(exc)
    first = text.splitlines()[0] if text else type(exc).__name__
    if isinstance(exc, MissingConfigException) and exc.options is not None and exc.missing_cfg_file:
        group, _, name = exc.missing_cfg_file.rpartition("/")
        return f"unknown {group} '{name}'; available: {', '.join(exc.options)} (choose with {group}=<name>)"
    if isinstance(exc, OverrideParseException):
        return f"cannot parse the override '{exc.override}': {first} (grammar: https://hydra.cc/docs/advanced/override_grammar/basic)"
    if m := re.match(r"Could not override '([^']+)'", first):
        return _unknown_key(m.group(1), re.search(r"use (\+\S+)", text))
    if m := re.match(r"Could not delete from config\. '([^']+)' does not exist", first):
        return f"~{m.group(1)}: there is no key {m.group(1)} to delete"
    if m := re.match(r"Ambiguous value for argument '([^']+)'", first):
        return (
            f"{m.group(1)}: a comma-separated value is a sweep: add -m to run one job per value; "
            "for a list write key=[a,b], for a string with commas quote it"
        )
    return first


def _unknown_key(key: str, append: re.Match | None) -> str:
    section, _, leaf = key.rpartition(".")
    node = _compose([])
    parent = OmegaConf.select(node, section) if section else node
    siblings = [str(k) for k in parent.keys()] if isinstance(parent, DictConfig) else []
    close = difflib.get_close_matches(leaf, siblings, n=1)
    hint = f"did you mean {section + '.' if section else ''}{close[0]}? " if close else ""
    added = append.group(1) if append else f"+{key}=…"
    if section == "reward":
        return (
            f"{key}: no such reward term; {hint}{added} adds a term registered by a plugin "
            "(python -m fallkit mode=list lists them)"
        )
    return f"{key}: no such key; {hint}python -m fallkit --cfg job prints every key"


def run(cfg: DictConfig) -> Any:
    """The task: validate, save the resolved config, dispatch to the mode."""
    try:
        raw = OmegaConf.to_container(cfg, resolve=True)
        config = validate(raw)
        if config.resume and config.mode == "train":
            config = _resume(config, raw)
            raw = {**raw, **config.model_dump(mode="json")}
        if config.experiment and HydraConfig.get().mode != RunMode.MULTIRUN:
            raise ConfigError(
                f"experiment={config.experiment} is a sweep of runs with a report: add -m "
                f"(python -m fallkit -m experiment={config.experiment})"
            )
        run_dir = Path(HydraConfig.get().runtime.output_dir)
        run_dir.mkdir(parents=True, exist_ok=True)
        (run_dir / "resolved_config.yaml").write_text(OmegaConf.to_yaml(raw))
        module, func = MODES[config.mode].split(":")
        handler: Callable[[FallkitConfig, Path], Any] = getattr(importlib.import_module(module), func)
        with running() if config.mode in CPU_HEAVY else contextlib.nullcontext():  # share the cores
            return handler(config, run_dir)
    except FallkitError as exc:
        fail(str(exc))


def _resume(config: FallkitConfig, raw: dict[str, Any]) -> FallkitConfig:
    """The run's own configuration with the command line's keys on top (fallkit.rl.resume)."""
    from fallkit.rl.resume import resume_config

    resumed = resume_config(config, _set_by_command_line(raw))
    if resumed.changed:
        print(f"resume: the command line changes the run's {'; '.join(resumed.changed)}")
    return resumed.config


def _set_by_command_line(raw: dict[str, Any]) -> set[str]:
    """Keys the command line set: those named in key=value overrides, and every key a group
    choice (train=quick, sim=warp) or override moved away from the defaults."""
    from fallkit.rl.resume import leaves

    hc = HydraConfig.get()
    groups = set(hc.runtime.choices)
    task = OverridesParser.create().parse_overrides(list(hc.overrides.task))
    named = {o.key_or_group for o in task if o.key_or_group not in groups}
    try:
        default = OmegaConf.to_container(compose(config_name="config", overrides=[]), resolve=True)
    except HydraException:  # a launcher's worker without Hydra's config loader: the groups as a whole
        return named | {o.key_or_group for o in task if o.key_or_group in groups}
    default.pop("hydra", None)
    now = leaves(validate({k: v for k, v in raw.items() if k != "hydra"}).model_dump(mode="json"))
    before = leaves(validate(default).model_dump(mode="json"))
    return named | {k for k, v in now.items() if before.get(k) != v}


@hydra.main(version_base="1.3", config_path="conf", config_name="config")
def _hydra_main(cfg: DictConfig) -> Any:
    return run(cfg)


def main() -> None:
    try:
        register_configs()
    except PluginError as exc:  # e.g. a robot name registered twice
        fail(str(exc))
    check_robot_overrides(sys.argv[1:])
    check_overrides(sys.argv[1:])
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
