"""Trained policies: load a checkpoint as a deterministic TensorDict module.

`load_policy(path).module` maps the actor observation ("policy") to the action
("action") with the Gaussian's mean; observation normalisation is inside it, so
it is the whole controller: setpoint = nominal + action_scale · action.
The networks compute in float32 whatever `train.precision` the run trained with: evaluation,
rendering, sim2sim and the ONNX export then run the same function of the same weights.
`load_policy(path).critic` is the trained value function V (privileged "critic"
observation -> value, normaliser inside) of Table I's reward weights (a checkpoint saved inside
train.early_reward_factor's schedule is rescaled to them): `eval.poses=auto` scores end poses with it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch
from tensordict.nn import TensorDictModule
from torch import nn

from fallkit.config import FallkitConfig, validate
from fallkit.errors import CheckpointError
from fallkit.rl.checkpoint import load_checkpoint
from fallkit.rl.models import GaussianPolicyNet, ValueNet, joint_prior
from fallkit.rl.reward_schedule import in_table_one_units
from fallkit.robots import robot_spec
from fallkit.robots.spec import RobotSpec


class MeanAction(nn.Module):
    """The deterministic controller: normalise, MLP, take the mean."""

    def __init__(self, net: GaussianPolicyNet):
        super().__init__()
        self.net = net

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.net(obs)[0]


@dataclass
class LoadedPolicy:
    module: TensorDictModule  # "policy" -> "action"
    config: FallkitConfig  # the training run's configuration
    spec: RobotSpec
    iteration: int
    path: Path
    critic: ValueNet | None = None  # [..., Dc] critic observation -> [..., 1] value, eval mode


def load_policy(path: str | Path, device: str | torch.device = "cpu") -> LoadedPolicy:
    ckpt = load_checkpoint(path, map_location=device)
    config = validate(ckpt["config"])
    spec = robot_spec(config.robot)
    if spec.model_hash() != ckpt["model_hash"]:
        raise CheckpointError(
            f"checkpoint {ckpt['path']} was trained on a different version of robot '{spec.name}' "
            f"(model {ckpt['model_hash']}, installed {spec.model_hash()})"
        )
    weights = {k.split("module.0.module.", 1)[1]: v for k, v in ckpt["actor"].items() if "module.0.module." in k}
    obs_dim = weights["norm.mean"].shape[0]
    act_dim = weights["log_std"].shape[0]
    net = GaussianPolicyNet(obs_dim, act_dim, config.train.actor_hidden, 1.0, joint_prior(config, spec))
    net.load_state_dict(weights)
    net.to(device).eval()
    module = TensorDictModule(MeanAction(net), in_keys=["policy"], out_keys=["action"])
    return LoadedPolicy(module, config, spec, int(ckpt["iteration"]), Path(ckpt["path"]), _critic(ckpt, config, device))


def _critic(ckpt: dict, config: FallkitConfig, device: str | torch.device) -> ValueNet:
    """The checkpoint's value network (a ValueOperator's state: "module.<ValueNet key>")."""
    weights = {k.removeprefix("module."): v for k, v in ckpt["critic"].items()}
    output = max(int(k.split(".")[1]) for k in weights if k.startswith("value."))  # the last Linear, with or without LayerNorms
    heads = weights[f"value.{output}.bias"].shape[0]  # > 1: a value per reward term
    columns = weights["weight_columns"].tolist() if "weight_columns" in weights else None  # w²-scaled impact heads
    net = ValueNet(weights["norm.mean"].shape[0], config.train.critic_hidden, "target.mean" in weights, heads=heads,
                   weight_columns=columns, layer_norm=config.train.critic_layer_norm)  # fmt: skip
    net.load_state_dict(weights)
    in_table_one_units(net, ckpt)
    return net.to(device).eval()
