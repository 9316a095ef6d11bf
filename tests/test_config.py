"""One source of defaults: the pydantic models in fallkit/config/; the Hydra YAML adds no value twice."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import yaml

import fallkit
from fallkit.app import composed_config as composed
from fallkit.config import (
    ConfigError,
    DatasetConfig,
    EnvConfig,
    EvalConfig,
    PPOConfig,
    RenderConfig,
    RewardConfig,
    SimConfig,
    TrainConfig,
    defaults,
)

CONF = Path(fallkit.__file__).parent / "conf"


def leaves(tree: Any, prefix: str = "") -> dict[str, Any]:
    if not isinstance(tree, dict):
        return {prefix: tree}
    out = {}
    for key, value in tree.items():
        out.update(leaves(value, f"{prefix}.{key}" if prefix else key))
    return out


def empty_dicts(tree: Any, prefix: str = "") -> set[str]:
    """The paths of the empty dicts in a config tree (`leaves` drops them)."""
    if not isinstance(tree, dict):
        return set()
    if not tree:
        return {prefix}
    return set().union(*(empty_dicts(v, f"{prefix}.{k}" if prefix else k) for k, v in tree.items()))


def test_the_root_yaml_holds_no_values():
    root = yaml.safe_load((CONF / "config.yaml").read_text())
    assert set(root) == {"defaults", "hydra"}


def test_composed_defaults_are_the_models_defaults():
    config = composed()
    assert config.env == EnvConfig() and config.reward == RewardConfig() and config.train == TrainConfig()
    assert config.eval == EvalConfig() and config.render == RenderConfig() and config.dataset == DatasetConfig()
    assert config.sim == SimConfig(num_envs=4096)  # the one value train=default adds: Table III's 4096 envs


# sim/ and train/ presets; experiment/ and scale/ set values on purpose over whatever came before them
@pytest.mark.parametrize("option", sorted(str(p.relative_to(CONF)) for g in ("sim", "train") for p in CONF.glob(f"{g}/*.yaml")))
def test_presets_only_write_values_that_differ_from_the_defaults(option):
    """A preset (sim/*.yaml, train/*.yaml) that repeats a default would be a second place to change it."""
    group = option.split("/")[0]
    text = (CONF / option).read_text()
    data = yaml.safe_load(text) or {}
    data.pop("defaults", None)
    tree = data if "@package _global_" in text else {group: data}
    base = leaves(defaults())
    for parent in (yaml.safe_load(text) or {}).get("defaults", []):  # built on another preset (train/default)
        base.update(leaves(yaml.safe_load((CONF / group / f"{parent}.yaml").read_text())))
    repeated = {k: v for k, v in leaves(tree).items() if k in base and base[k] == v}
    assert not repeated, f"{option} repeats defaults: {repeated}"
    known = set(base) | {k.rsplit(".", n)[0] for k in base for n in range(1, k.count(".") + 1)}  # or a whole dict
    free = empty_dicts(defaults())  # a dict of the user's keys, empty by default (train.early_reward_factor)
    unknown = sorted(k for k in set(leaves(tree)) - known if not any(k.startswith(f"{d}.") for d in free))
    # (train/paper.yaml: `term_lam: null` empties the default's)
    assert not unknown, f"{option} sets keys no model has: {unknown}"


def test_presets_compose_and_change_what_they_say():
    quick = composed("train=quick")
    assert quick.sim.num_envs == 1024 and quick.train.max_minutes == 15 and quick.train.actor_hidden == [256, 256, 256]
    # 12-step rollouts in 8 minibatches: the 1536-sample minibatch of 256 worlds × 24 steps, twice the updates
    assert (quick.train.num_steps, quick.train.ppo.num_minibatches) == (12, 8)
    assert quick.train.critic_hidden == [128, 128, 128]  # the update's larger half, halved in width
    with pytest.raises(ConfigError, match=r"num_minibatches=8 leaves fewer than 2 samples per minibatch in a batch "
                       r"of 12 \(sim.num_envs=1 × train.num_steps=12\): lower train.ppo.num_minibatches"):
        composed("train=quick", "sim.num_envs=1")
    assert composed("train=quick", "sim.num_envs=2").sim.num_envs == 2  # 24 samples: 3 per minibatch
    with pytest.raises(ConfigError, match=r"train.ppo.late_num_minibatches=32 leaves fewer than 2 samples per "
                       r"minibatch in a batch of 24 .* lower train.ppo.late_num_minibatches or raise sim.num_envs"):
        composed("train=quick", "sim.num_envs=2", "train.ppo.late_num_minibatches=32")
    warp = composed("sim=warp")
    assert warp.sim.backend == "warp" and warp.sim.device == "auto" and warp.sim.threads == SimConfig().threads
    # train=quick on a GPU: quick's networks and std, the GPU's 4096 worlds in 4 big minibatches
    gpu = composed("sim=warp", "train=quick_gpu")
    assert gpu.sim.backend == "warp" and (gpu.sim.num_envs, gpu.train.num_steps, gpu.train.ppo.num_minibatches) == (4096, 24, 4)
    assert gpu.train.actor_hidden == quick.train.actor_hidden and gpu.train.init_noise_std == quick.train.init_noise_std
    assert gpu.train.max_minutes == 10 and gpu.train.ppo.term_lam == quick.train.ppo.term_lam
    # train=quick for an hour on the same CPU, in the 24-step rollouts it was measured with: the budget and,
    # after 6 M env steps, 4 bigger minibatches differ
    hour = composed("train=hour")
    assert hour.train.early_reward_factor == quick.train.early_reward_factor == {"orientation": 5}
    assert (hour.sim.num_envs, hour.train.num_steps, hour.train.ppo.num_minibatches, hour.train.max_minutes) == (1024, 24, 16, 60)
    assert [hour.train.ppo.minibatches_at(steps) for steps in (0, 5_999_999, 6_000_000)] == [16, 16, 4]
    assert quick.train.ppo.minibatches_at(10**9) == 8  # no schedule: num_minibatches throughout
    assert hour.train.actor_hidden == quick.train.actor_hidden and hour.train.ppo.term_lam == quick.train.ppo.term_lam
    assert hour.train.critic_hidden == gpu.train.critic_hidden == [256, 256, 256]  # as each was measured
    assert quick.train.ppo.kl_stop == 2 and hour.train.ppo.kl_stop is gpu.train.ppo.kl_stop is None


def test_train_paper_is_the_papers_setting_and_seek_needs_the_clock():
    paper = composed("train=paper")
    assert paper.train.prior == "none" and not paper.env.observe_blend and paper.train.init_noise_std == 1.0
    assert paper.sim.num_envs == 4096 and paper.train.actor_hidden == [512, 512, 512] and not paper.train.fade_residual
    assert paper.train.precision == "float32" and composed().train.precision == "auto"
    table_iii = PPOConfig(critic_learning_rate=None, value_clip=0.2, normalize_value=False, value_per_term=False,
                          prior_coef=0.0)  # fmt: skip
    assert composed().train.ppo.prior_coef == composed("train=quick").train.ppo.prior_coef == 0.03
    assert composed().train.ppo.value_per_term and composed("train=quick").train.ppo.value_per_term
    # the orientation term's own λ is the default's, and the paper's one value has one λ
    assert composed().train.ppo.term_lam == composed("train=quick").train.ppo.term_lam == {"orientation": 0.4}
    assert paper.train.ppo.term_lam == {} and composed("train.ppo.value_per_term=false").train.ppo.term_lam == {}
    assert composed("train.ppo.term_lam=null").train.ppo.term_lam == {}  # lam for every term
    assert not paper.env.observe_gravity and not paper.env.sensitivity_inputs.enabled
    assert paper.train.ppo == table_iii and (table_iii.num_minibatches, table_iii.epochs, table_iii.desired_kl) == (4, 5, 0.01)
    with pytest.raises(ConfigError, match="train.prior=seek blends by u"):
        composed("env.observe_blend=false")
    with pytest.raises(ConfigError, match="train.fade_residual fades the MLP"):
        composed("env.observe_blend=false", "train.prior=hold")
    assert composed("env.observe_blend=false", "train.prior=hold", "train.fade_residual=false").train.prior == "hold"
    # the paper's MLP alone: every setting that needs a prior is named in one line, and off they compose
    with pytest.raises(ConfigError, match="no prior for train.fade_residual and train.ppo.prior_coef: set"):
        composed("train.prior=none")
    with pytest.raises(ConfigError, match="no prior for train.ppo.prior_coef: set"):
        composed("train.prior=none", "train.fade_residual=false")
    assert composed("train.prior=none", "train.fade_residual=false", "train.ppo.prior_coef=0").train.prior == "none"


def test_a_bad_override_is_one_line_naming_the_key():
    """composed_config, which benchmarks and notebooks call, says what the command line says (no Hydra traceback)."""
    with pytest.raises(ConfigError, match=r"^train.nosuch: no such key; python -m fallkit --cfg job prints every key$"):
        composed("train.nosuch=1")
