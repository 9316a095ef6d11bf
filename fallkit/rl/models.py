"""Actor and critic networks (paper Sec. V-A): ELU MLPs, a Gaussian policy with a learned
state-independent standard deviation, and running observation normalisation.

The normalisers live inside the networks, so a checkpoint's state_dict carries
them and an exported policy normalises its own inputs.
"""

from __future__ import annotations

import torch
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.modules import IndependentNormal, ProbabilisticActor, ValueOperator

from fallkit.config import FallkitConfig
from fallkit.env.observations import actor_slices
from fallkit.robots.spec import RobotSpec


class RunningNorm(nn.Module):
    """Running mean/variance of observations; `update` changes the buffers in place.

    In place matters: a collecting policy that shares these buffers sees the new
    statistics at once (replacing the tensors left it with stale ones — NOTES).
    """

    def __init__(self, dim: int, clip: float = 5.0, eps: float = 1e-8):
        super().__init__()
        self.clip, self.eps = clip, eps
        self.register_buffer("mean", torch.zeros(dim))
        self.register_buffer("var", torch.ones(dim))
        self.register_buffer("count", torch.zeros(()))

    @torch.no_grad()
    def update(self, x: torch.Tensor) -> None:
        """Merge a batch [..., dim] into the statistics (parallel-variance formula)."""
        x = x.reshape(-1, x.shape[-1]).to(self.mean.dtype)
        n = x.shape[0]
        if n == 0:
            return
        mean, var = x.mean(0), x.var(0, unbiased=False)
        total = self.count + n
        delta = mean - self.mean
        m2 = self.var * self.count + var * n + delta.square() * self.count * n / total
        self.mean.add_(delta * n / total)
        self.var.copy_(m2 / total)
        self.count.fill_(total)

    def merge_(self, mean: torch.Tensor, var: torch.Tensor, count: torch.Tensor) -> None:
        """Set the statistics (e.g. after averaging them across distributed ranks)."""
        self.mean.copy_(mean)
        self.var.copy_(var)
        self.count.copy_(count)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return ((x - self.mean) / torch.sqrt(self.var + self.eps)).clamp(-self.clip, self.clip)


def mlp(in_dim: int, hidden: list[int], out_dim: int) -> nn.Sequential:
    layers: list[nn.Module] = []
    for h in hidden:
        layers += [nn.Linear(in_dim, h), nn.ELU()]
        in_dim = h
    layers.append(nn.Linear(in_dim, out_dim))
    return nn.Sequential(*layers)


class HoldPrior(nn.Module):
    """The action that holds the measured joint angles: (q − nominal) / action_scale.

    Added to the MLP's output, it makes an untrained policy hold whatever pose the
    robot is in (setpoint = measured angles: pure joint damping), which is where the
    standard fall strategies start, instead of yanking every joint toward the
    standing pose. The MLP learns the deviation from holding.
    """

    def __init__(self, joint_columns: torch.Tensor, nominal: torch.Tensor, action_scale: float):
        super().__init__()
        self.register_buffer("joint_columns", joint_columns.long())
        self.register_buffer("nominal", nominal.float())
        self.register_buffer("inv_scale", torch.tensor(1.0 / action_scale))

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return (obs[..., self.joint_columns] - self.nominal) * self.inv_scale


def hold_prior(config: FallkitConfig, spec: RobotSpec) -> HoldPrior | None:
    """The policy's hold prior for this robot and action scale, if `train.hold_prior` asks for it."""
    if not config.train.hold_prior:
        return None
    joints = actor_slices(spec)["joint_pos"]
    return HoldPrior(torch.arange(joints.start, joints.stop), torch.as_tensor(spec.nominal_q()), config.env.action_scale)


class GaussianPolicyNet(nn.Module):
    """obs -> (loc, scale); scale = exp(log_std), a learned parameter independent of the state."""

    def __init__(self, obs_dim: int, act_dim: int, hidden: list[int], init_std: float, hold: HoldPrior | None = None):
        super().__init__()
        self.norm = RunningNorm(obs_dim)
        self.mean = mlp(obs_dim, hidden, act_dim)
        self.hold = hold
        self.log_std = nn.Parameter(torch.full((act_dim,), float(torch.log(torch.tensor(init_std)))))
        # Small last layer: the first actions are the prior's (or the nominal pose without one).
        nn.init.uniform_(self.mean[-1].weight, -1e-3, 1e-3)
        nn.init.zeros_(self.mean[-1].bias)

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        loc = self.mean(self.norm(obs))
        if self.hold is not None:
            loc = loc + self.hold(obs)
        return loc, self.log_std.exp().expand_as(loc)


class ValueNet(nn.Module):
    def __init__(self, obs_dim: int, hidden: list[int]):
        super().__init__()
        self.norm = RunningNorm(obs_dim)
        self.value = mlp(obs_dim, hidden, 1)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.value(self.norm(obs))


def make_actor(
    obs_dim: int, act_dim: int, hidden: list[int], init_std: float, hold: HoldPrior | None = None, action_spec=None
) -> ProbabilisticActor:
    """TensorDict keys: "policy" -> "loc", "scale" -> "action" (+ "action_log_prob")."""
    net = TensorDictModule(
        GaussianPolicyNet(obs_dim, act_dim, hidden, init_std, hold), in_keys=["policy"], out_keys=["loc", "scale"]
    )
    return ProbabilisticActor(
        net,
        in_keys=["loc", "scale"],
        out_keys=["action"],
        spec=action_spec,
        distribution_class=IndependentNormal,
        return_log_prob=True,
        log_prob_key="action_log_prob",
    )


def make_critic(obs_dim: int, hidden: list[int]) -> ValueOperator:
    """TensorDict keys: "critic" -> "state_value"."""
    return ValueOperator(ValueNet(obs_dim, hidden), in_keys=["critic"], out_keys=["state_value"])


def policy_net(actor: ProbabilisticActor) -> GaussianPolicyNet:
    return actor.module[0].module


def value_net(critic: ValueOperator) -> ValueNet:
    return critic.module
