"""`train.init_from=<run or checkpoint>`: a new training run whose networks start as a trained policy's.

`resume=` continues a run exactly (its config, optimizer, envs, iteration). `init_from` starts a new run —
its own config, envs, optimizer moments and iteration 0 — from another run's actor and critic: their
weights, observation statistics and action std. The use: teaching a policy that already falls softly one
more thing without paying again for what it knows, or training on with other settings. Tried for sensitivity
inputs (`env.sensitivity_inputs.enabled=true`), where a policy trained from scratch spends its budget learning
to soften falls before it reads six extra inputs: started from a policy that falls softly it did not read them
sooner (docs/sensitivity_inputs.md).

Observation columns are matched by part name (fallkit.env.observations: actor_layout, critic_layout), so
the new run may observe more than the loaded one did: the first layer's weights from a part the loaded
policy did not observe start at zero — the new run's first actions are the loaded policy's, to rounding —
and those columns' running statistics are set from the run's first observations (`fresh_statistics`). What
would change what the loaded weights mean is refused with one line: another robot model, other network
sizes or value heads, another prior or action scale, or a part the loaded policy observed and this run
does not.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import torch
from torch import nn

from fallkit.config import FallkitConfig
from fallkit.env.observations import actor_layout, critic_layout
from fallkit.errors import CheckpointError, ConfigError
from fallkit.rl.checkpoint import load_checkpoint
from fallkit.rl.models import RunningNorm, value_net
from fallkit.rl.reward_schedule import in_table_one_units
from fallkit.robots.spec import RobotSpec

log = logging.getLogger(__name__)

# What a loaded actor's outputs mean as actions (train.teachers checks these), and with the critic's value
# scale what all the loaded weights mean (train.init_from): these must be the loaded run's.
ACTION_MEANING = ("train.prior", "train.fade_residual", "train.prior_power", "env.action_scale")
_SAME_MEANING = (*ACTION_MEANING, "train.ppo.normalize_value")


@dataclass
class NewColumns:
    """Observation columns of this run that the loaded networks did not observe (their statistics start
    from the first observations)."""

    policy: torch.Tensor
    critic: torch.Tensor


def start_from(where: str, actor: nn.Module, critic: nn.Module, config: FallkitConfig, spec: RobotSpec,
               device: torch.device | str) -> tuple[NewColumns, float]:  # fmt: skip
    """Load the actor and critic of checkpoint `where` (a file or a run directory) into this run's `actor` and
    `critic` (the modules of fallkit.rl.models.make_actor and make_critic, as checkpoints save them); returns
    the columns new to them and the loaded run's last actor learning rate (where the KL rule starts)."""
    try:
        ckpt = load_checkpoint(where, map_location=device)
    except CheckpointError as exc:
        raise CheckpointError(f"train.init_from: {exc}") from None
    path, saved = ckpt["path"], ckpt["config"]
    say = f"train.init_from: {path}"
    if ckpt["model_hash"] != spec.model_hash():
        raise ConfigError(f"{say} was trained on robot '{ckpt['robot']}', another model than this run's "
                          f"'{spec.name}': start from a policy of the same robot model")  # fmt: skip
    now = config.model_dump(mode="json")
    same_meaning(saved, now, say)
    before, after = observation_options(saved), observation_options(now)
    columns = {}
    for name, net, layout in (("policy", actor, actor_layout), ("critic", critic, critic_layout)):
        index = column_map(layout(spec, *before), layout(spec, *after), f"{say}: the {name} observation")
        columns[name] = _load_net(net, ckpt["actor" if name == "policy" else "critic"], index, name, say)
    in_table_one_units(value_net(critic), ckpt)
    rate = float(ckpt["ppo"]["learning_rate"]) if "learning_rate" in ckpt.get("ppo", {}) else config.train.ppo.learning_rate
    log.info("networks start from %s (iteration %d); observation columns new to them, at zero weight: %d of the "
             "actor's, %d of the critic's", path, ckpt["iteration"], columns["policy"].numel(), columns["critic"].numel())  # fmt: skip
    return NewColumns(**columns), rate


@torch.no_grad()
def fresh_statistics(norm: RunningNorm, columns: torch.Tensor, obs: torch.Tensor) -> None:
    """The running mean and variance of `columns` from these observations: the loaded statistics' count is
    that of a whole training, and would hold new inputs at mean 0 and variance 1 for as long."""
    if columns.numel() == 0:
        return
    x = obs.reshape(-1, obs.shape[-1])[:, columns].to(norm.mean.dtype)
    norm.mean[columns] = x.mean(0)
    norm.var[columns] = x.var(0, unbiased=False)


def same_meaning(saved: dict, now: dict, say: str, keys: tuple[str, ...] = _SAME_MEANING) -> None:
    """Refuse, in one line, a loaded run (config `saved`, as its checkpoint stores it) whose weights mean
    something else than this run's (`now`) under `keys`: another prior, fade, prior power, action scale or value
    scale."""
    for key in keys:
        theirs, ours = _get(saved, key), _get(now, key)
        if theirs != ours:
            raise ConfigError(f"{say} was trained with {key}={theirs}, this run has {ours}: set {key}={theirs}")


def observation_options(config: dict) -> tuple[bool, bool]:
    """The observation options of a config (as actor_layout takes them): sensitivity inputs, observed gravity."""
    env = config["env"]
    return bool(env.get("sensitivity_inputs", {}).get("enabled", False)), bool(env.get("observe_gravity", False))


def column_map(before: list[tuple[str, int]], after: list[tuple[str, int]], what: str) -> torch.Tensor:
    """For each column of the loaded layout, its column in this run's."""
    starts, at = {}, 0
    for name, size in after:
        starts[name] = (at, size)
        at += size
    index = []
    for name, size in before:
        if name not in starts:
            raise ConfigError(f"{what} has part '{name}', which this run does not observe: switch its option on")
        start, now = starts[name]
        if now != size:
            raise ConfigError(f"{what}'s part '{name}' has {size} columns, this run's {now}")
        index.extend(range(start, start + size))
    return torch.tensor(index, dtype=torch.long)


def _load_net(net: nn.Module, state: dict[str, torch.Tensor], index: torch.Tensor, name: str, say: str) -> torch.Tensor:
    """`state` into `net` with the input columns moved by `index`; returns the columns of `net` not in `index`."""
    own = net.state_dict()
    first = next(k for k in own if k.endswith(".weight"))  # the first Linear: the only one that sees observations
    inputs = {k for k in own if k.endswith(("norm.mean", "norm.var"))}  # the observation statistics, per column
    keys = [k for k in own if ".prior." not in k and not k.endswith("weight_columns")]  # this run's layout, not theirs
    for key in keys:
        if key not in state:
            raise ConfigError(f"{say}: its {name} network has no '{key}' (another train.ppo.normalize_value or train.critic_layer_norm?)")
        theirs = state[key]
        shape = (own[key].shape[0], index.numel()) if key == first else (
            (index.numel(),) if key in inputs else own[key].shape)  # fmt: skip
        if theirs.shape != shape:
            raise ConfigError(f"{say}: its {name} network's {key} has shape {tuple(theirs.shape)}, this run's "
                              f"{tuple(shape)}: use the loaded run's network sizes and value heads "
                              "(train.actor_hidden, train.critic_hidden, train.ppo.value_per_term/value_per_component)")  # fmt: skip
    for key in keys:
        theirs = state[key].to(own[key].dtype)
        if key == first:
            own[key].zero_()
            own[key][:, index] = theirs
        elif key in inputs:
            own[key][index] = theirs
        else:
            own[key].copy_(theirs)
    net.load_state_dict(own)
    new = torch.ones(own[first].shape[1], dtype=torch.bool)
    new[index] = False
    return new.nonzero().squeeze(-1)


def _get(tree: dict, key: str):
    for part in key.split("."):
        tree = tree.get(part) if isinstance(tree, dict) else None
    return tree
