"""The Hydra app: composition, plugin robots in ConfigStore, one-line errors, multirun."""

from __future__ import annotations

import os
import re
import subprocess
import sys

import pytest
import yaml
from helpers import fallkit_cli
from hydra import compose, initialize_config_module
from hydra.core.global_hydra import GlobalHydra
from omegaconf import OmegaConf

from fallkit.app import register_configs
from fallkit.config import ConfigError, validate
from fallkit.robots import robot_spec


def composed(*overrides: str):
    GlobalHydra.instance().clear()
    register_configs()
    with initialize_config_module(config_module="fallkit.conf", version_base="1.3"):
        cfg = compose(config_name="config", overrides=list(overrides))
    return OmegaConf.to_container(cfg, resolve=False)


def test_defaults_compose_and_validate():
    raw = composed()
    raw.pop("hydra", None)
    config = validate(raw)
    assert config.mode == "train" and config.robot.name == "biped20" and config.sim.backend == "mujoco"
    assert config.robot.sensitivity["head"] == 4.0  # the robot node carries the spec's weights


def test_robot_group_comes_from_the_registry():
    raw = composed("robot=biped20_battery", "robot.sensitivity.battery=7.5")
    raw.pop("hydra", None)
    spec = robot_spec(validate(raw).robot)
    assert spec.components["battery"].weight == 7.5 and spec.components["head"].weight == 1.0


@pytest.mark.parametrize(
    "override, message",
    [
        ("sim.num_envs=-3", "sim.num_envs: Input should be greater than 0 (got -3)"),
        ("eval.trials=abc", "eval.trials: Input should be a valid integer"),
        ("mode=dance", "mode: Input should be"),
        ("robot.sensitivity.head=-1", "robot.sensitivity: weights must be >= 0"),
        ("train.ppo.lr_min=0.1 train.ppo.lr_max=0.01", "train.ppo.learning_rate=0.001 must lie in [lr_min, lr_max] = [0.1, 0.01]"),
        ("train.ppo.lr_max=1e-4", "train.ppo.learning_rate=0.001 must lie in [lr_min, lr_max] = [1e-05, 0.0001]"),
    ],
)
def test_wrong_values_are_one_clear_error(override, message):
    raw = composed(*override.split())
    raw.pop("hydra", None)
    with pytest.raises(ConfigError, match=re.escape(message)):
        robot_spec(validate(raw).robot)


def test_cli_unknown_robot_is_one_line(tmp_path):
    r = fallkit_cli("robot=nosuch", cwd=tmp_path)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "unknown robot 'nosuch'" in lines[0] and "biped20_battery" in lines[0]


def test_cli_bad_value_is_one_line(tmp_path):
    r = fallkit_cli("mode=eval", "sim.num_envs=-1", cwd=tmp_path)
    assert r.returncode == 2
    assert r.stderr.strip().splitlines() == ["fallkit: error: sim.num_envs: Input should be greater than 0 (got -1)"]


def test_a_config_error_answers_before_torch_is_imported(tmp_path):
    """Composition, validation and the robot registry import no torch (2-3 s on a small CPU): a typo is
    answered in about 2 s instead of 5. A top-level torch import on that path fails here."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    r = subprocess.run([sys.executable, "-X", "importtime", "-m", "fallkit", "robot=go1", "sim.num_envs=-1"],
                       cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)  # fmt: skip
    assert r.returncode == 2, r.stderr
    assert r.stderr.strip().splitlines()[-1] == "fallkit: error: sim.num_envs: Input should be greater than 0 (got -1)"
    imported = {line.rsplit("|", 1)[-1].strip() for line in r.stderr.splitlines() if line.startswith("import time:")}
    assert "fallkit.robots" in imported  # the robot registry ran (robot=go1: a plugin's URDF robot)
    assert not {m for m in imported if m == "torch" or m.startswith("torch.")}, "torch imported before a mode ran"


def test_cli_list_shows_distributions(tmp_path):
    r = fallkit_cli("mode=list", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert "fallkit.robots:" in r.stdout and "fallkit.rewards:" in r.stdout and "fallkit.samplers:" in r.stdout
    line = next(l for l in r.stdout.splitlines() if l.strip().startswith("biped20 "))
    assert "fallkit (fallkit.robots.biped20:biped20)" in line


def test_cli_multirun_writes_one_dir_per_job_with_resolved_config(tmp_path):
    r = fallkit_cli("-m", "mode=eval", "eval.trials=2", "eval.seconds=0.1,0.2", "hydra.sweep.dir=sweep", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    dirs = sorted(p for p in (tmp_path / "sweep").iterdir() if p.is_dir())
    assert len(dirs) == 2
    seconds = sorted(yaml.safe_load((d / "resolved_config.yaml").read_text())["eval"]["seconds"] for d in dirs)
    assert seconds == [0.1, 0.2]
    assert all((d / "eval.json").is_file() for d in dirs)
