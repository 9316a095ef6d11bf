"""Actor and critic networks (paper Sec. V-A): ELU MLPs, a Gaussian policy with a learned
state-independent standard deviation, and running observation normalisation.

The normalisers live inside the networks, so a checkpoint's state_dict carries
them and an exported policy normalises its own inputs.
"""

from __future__ import annotations

from typing import Literal

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


Precision = Literal["float32", "bfloat16"]


def resolve_precision(precision: str, device: torch.device | str) -> Precision:
    """train.precision on this device: "auto" is bfloat16 where it was measured to pay — a CPU with
    AVX512-BF16 (the PPO update 1.9x as fast, docs/training.md) — and float32 elsewhere (other CPUs
    would emulate it; on a GPU it is unmeasured: set it there by hand)."""
    if precision != "auto":
        return precision  # type: ignore[return-value]
    check = getattr(torch.cpu, "_is_avx512_bf16_supported", None)  # private: absent in other torch versions
    return "bfloat16" if torch.device(device).type == "cpu" and check is not None and check() else "float32"


def run_mlp(layers: nn.Sequential, x: torch.Tensor, precision: Precision) -> torch.Tensor:
    """The MLP's output in float32; with "bfloat16" its matrix products run in bfloat16 under autocast
    (weights stay float32, products accumulate in float32), twice as fast on a CPU with AVX512-BF16
    (train.precision, docs/training.md). The same arithmetic collects and learns, so the collecting
    policy's log-probabilities are the update's at zero step; a trained policy is evaluated and exported
    in float32 (fallkit.rl.policy)."""
    if precision == "float32":
        return layers(x)
    if precision != "bfloat16":
        raise ValueError(f"precision {precision!r}: float32 or bfloat16 (resolve 'auto' with resolve_precision)")
    with torch.autocast(x.device.type, dtype=torch.bfloat16):
        return layers(x).float()


def mlp(in_dim: int, hidden: list[int], out_dim: int, layer_norm: bool = False) -> nn.Sequential:
    """ELU MLP; with `layer_norm` each hidden layer is Linear, LayerNorm, ELU (train.critic_layer_norm)."""
    layers: list[nn.Module] = []
    for h in hidden:
        layers += [nn.Linear(in_dim, h), *([nn.LayerNorm(h)] if layer_norm else []), nn.ELU()]
        in_dim = h
    layers.append(nn.Linear(in_dim, out_dim))
    return nn.Sequential(*layers)


class JointPrior(nn.Module):
    """The action of a joint setpoint read off the observation; the MLP learns the deviation from it.

    hold: the measured joint angles, (q − nominal) / action_scale. An untrained policy then
          holds whatever pose the robot is in (pure joint damping), where the standard fall
          strategies start, instead of yanking every joint toward the standing pose.
    seek: q + u(t)^p·(q̂ − q) (p = train.prior_power), with u(t) the tracking blend the actor observes: the hold while
          the fall begins, turning into the target joints q̂ as the reward's tracking terms
          come in. Seeking from the start made landings harder (max impact 1.09× the best
          strategy, docs/training.md); blended, the prior leaves the impact phase to the hold.
    """

    def __init__(self, spec: RobotSpec, action_scale: float, seek: bool, fade: bool = False, power: float = 1.0):
        super().__init__()
        columns = actor_slices(spec)
        self.seek, self.fade, self.power = seek, fade, float(power)
        for name in ("joint_pos", "goal_joint_pos", "blend"):
            self.register_buffer(f"{name}_columns", torch.arange(columns[name].start, columns[name].stop))
        self.register_buffer("nominal", torch.as_tensor(spec.nominal_q()).float())
        self.register_buffer("inv_scale", torch.tensor(1.0 / action_scale))

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        q = obs[..., self.joint_pos_columns]
        if self.seek:
            q = torch.lerp(q, obs[..., self.goal_joint_pos_columns], self.blend(obs))
        return (q - self.nominal) * self.inv_scale

    def blend(self, obs: torch.Tensor) -> torch.Tensor:
        """The prior's own blend u(t)^power from the observed u(t): with power > 1 the hold and the
        learned deviation keep the fall longer and the prior takes the joints late (train.prior_power)."""
        u = obs[..., self.blend_columns]
        return u if self.power == 1.0 else u.clamp(min=0.0).pow(self.power)

    def residual_weight(self, obs: torch.Tensor) -> torch.Tensor:
        """How much of the MLP's deviation the policy mean keeps: 1 − u(t)^power with `fade`, else 1.

        Fading hands the end of the fall to the prior: the deviation learned for the impact
        phase does not leak into the final pose (without it, MJE 0.24 rad where seek alone
        reaches 0.06, docs/training.md).
        """
        u = self.blend(obs)
        return 1.0 - u if self.fade else torch.ones_like(u)


def joint_prior(config: FallkitConfig, spec: RobotSpec) -> JointPrior | None:
    """The policy's prior (`train.prior`: none | hold | seek) for this robot and action scale."""
    if config.train.prior == "none":
        return None
    tc = config.train
    return JointPrior(spec, config.env.action_scale, seek=tc.prior == "seek", fade=tc.fade_residual, power=tc.prior_power)


class GaussianPolicyNet(nn.Module):
    """obs -> (loc, scale); scale = exp(log_std), a learned parameter independent of the state.

    With `noise_floor` f (train.fade_noise, needs a fading prior) the scale fades with the learned
    deviation, exp(log_std)·(f + (1 − f)·residual_weight): where the mean is the prior's alone, full
    noise explores nothing the policy can change and only shakes the landing that the orientation
    and joint terms judge (a deterministic evaluation never sees it).
    """

    def __init__(
        self,
        obs_dim: int,
        act_dim: int,
        hidden: list[int],
        init_std: float,
        prior: JointPrior | None = None,
        noise_floor: float | None = None,
        precision: Precision = "float32",
    ):
        super().__init__()
        if noise_floor is not None and (prior is None or not prior.fade):
            raise ValueError("GaussianPolicyNet: noise_floor fades the noise with the residual: it needs a fading prior")
        self.norm = RunningNorm(obs_dim)
        self.mean = mlp(obs_dim, hidden, act_dim)
        self.prior = prior
        self.noise_floor = noise_floor
        self.precision = precision
        self.log_std = nn.Parameter(torch.full((act_dim,), float(torch.log(torch.tensor(init_std)))))
        # Small last layer: the first actions are the prior's (or the nominal pose without one).
        nn.init.uniform_(self.mean[-1].weight, -1e-3, 1e-3)
        nn.init.zeros_(self.mean[-1].bias)

    def deviation(self, obs: torch.Tensor) -> torch.Tensor:
        """The learned deviation: the MLP's share of the policy mean (all of it without a prior)."""
        loc = run_mlp(self.mean, self.norm(obs), self.precision)
        return loc if self.prior is None else loc * self.prior.residual_weight(obs)

    def forward(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        loc = run_mlp(self.mean, self.norm(obs), self.precision)
        scale = self.log_std.exp().expand_as(loc)
        if self.prior is not None:
            weight = self.prior.residual_weight(obs)
            loc = torch.addcmul(self.prior(obs), loc, weight)
            if self.noise_floor is not None:
                scale = scale * (self.noise_floor + (1.0 - self.noise_floor) * weight)
        return loc, scale


class ValueNet(nn.Module):
    """obs -> state value [..., heads]. With `normalize_target` the MLP predicts the value in units of the
    running statistics of the value targets (`target`), and the output is scaled back: value targets of
    about −50 with a std of about 40 (biped20, train=quick) become O(1) targets (train.ppo.normalize_value).
    With heads > 1 (train.ppo.value_per_term) head k is the value of reward term k alone; V(s) is their sum.

    `weight_columns` (one per head, −1 for none) name, for a head that predicts a component's impact
    (train.ppo.value_per_component) of a policy with sensitivity inputs, the observation column holding
    ln w_c: that head's output is multiplied by w_c² = exp(2 ln w_c). The component's impact reward is
    w_c² times its unweighted impact, so the MLP learns the unweighted return, whose scale does not move
    with the weight drawn for the episode (0.04 … 25 × the robot's over ln-uniform 0.2 … 5 weights).
    Kept as a buffer, so a loaded checkpoint scales as in training.
    """

    def __init__(
        self,
        obs_dim: int,
        hidden: list[int],
        normalize_target: bool = False,
        precision: Precision = "float32",
        heads: int = 1,
        weight_columns: list[int] | None = None,
        layer_norm: bool = False,
    ):
        super().__init__()
        self.norm = RunningNorm(obs_dim)
        self.value = mlp(obs_dim, hidden, heads, layer_norm)
        self.precision = precision
        self.target = RunningNorm(heads) if normalize_target else None
        scaled = weight_columns is not None and any(c >= 0 for c in weight_columns)
        if scaled and (normalize_target or len(weight_columns) != heads):
            raise ValueError("ValueNet: weight_columns need one entry per head and no target normalisation")
        columns = torch.tensor(weight_columns, dtype=torch.long) if scaled else None
        self.register_buffer("weight_columns", columns)  # None: not in the state dict (older checkpoints load)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        v = run_mlp(self.value, self.norm(obs), self.precision)
        if self.target is not None:
            v = torch.addcmul(self.target.mean, v, self.target_std())
        if self.weight_columns is not None:
            squared_weight = torch.exp(2.0 * obs[..., self.weight_columns.clamp(min=0)])
            v = torch.where(self.weight_columns >= 0, v * squared_weight, v)
        return v

    def target_std(self) -> torch.Tensor:
        return torch.sqrt(self.target.var + self.target.eps)

    @torch.no_grad()
    def scale_heads(self, factor: torch.Tensor) -> None:
        """Every head's prediction times its factor [heads], exactly: the last layer's rows (and, with target
        normalisation, the statistics' mean) scaled — for a reward term whose weight changed by that factor
        (fallkit.rl.reward_schedule), whose return is linear in it."""
        last = self.value[-1]
        factor = factor.to(last.weight)
        last.weight.mul_(factor.unsqueeze(-1))
        last.bias.mul_(factor)
        if self.target is not None:  # v = mean + std·(W h + b): mean and (W, b) by the factor, std kept
            self.target.mean.mul_(factor.to(self.target.mean))

    @torch.no_grad()
    def update_target_statistics(self, targets: torch.Tensor, merge=None) -> None:
        """Merge value targets into `target` (then `merge(target)`, e.g. across ranks) and rescale the last
        layer so every value the network predicts stays what it was (PopArt's preserving step): the
        statistics move, the values GAE and the loss already hold stay true."""
        old_mean, old_std = self.target.mean.clone(), self.target_std()
        self.target.update(targets.reshape(-1, self.target.mean.shape[0]))
        if merge is not None:
            merge(self.target)
        new_mean, new_std = self.target.mean, self.target_std()
        last = self.value[-1]
        last.weight.mul_((old_std / new_std).unsqueeze(-1))
        last.bias.mul_(old_std).add_(old_mean - new_mean).div_(new_std)


def make_actor(
    obs_dim: int,
    act_dim: int,
    hidden: list[int],
    init_std: float,
    prior: JointPrior | None = None,
    action_spec=None,
    noise_floor: float | None = None,
    precision: Precision = "float32",
) -> ProbabilisticActor:
    """TensorDict keys: "policy" -> "loc", "scale" -> "action" (+ "action_log_prob")."""
    net = TensorDictModule(
        GaussianPolicyNet(obs_dim, act_dim, hidden, init_std, prior, noise_floor, precision),
        in_keys=["policy"],
        out_keys=["loc", "scale"],
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


def impact_weight_columns(spec: RobotSpec, heads: list[str], gravity: bool = False) -> list[int]:
    """For a critic with sensitivity inputs, each value head's column of ln w_c in the critic observation
    (which starts with the actor's): that of component c for head "impact/<c>", −1 for every other head."""
    start = actor_slices(spec, sensitivity=True, gravity=gravity)["sensitivity"].start
    index = {f"impact/{c}": start + i for i, c in enumerate(spec.component_names)}
    return [index.get(name, -1) for name in heads]


def make_critic(
    obs_dim: int,
    hidden: list[int],
    normalize_target: bool = False,
    precision: Precision = "float32",
    heads: int = 1,
    weight_columns: list[int] | None = None,
    layer_norm: bool = False,
) -> ValueOperator:
    """TensorDict keys: "critic" -> "state_value" [..., heads]."""
    net = ValueNet(obs_dim, hidden, normalize_target, precision, heads, weight_columns, layer_norm)
    return ValueOperator(net, in_keys=["critic"], out_keys=["state_value"])


def policy_net(actor: ProbabilisticActor) -> GaussianPolicyNet:
    return actor.module[0].module


def value_net(critic: ValueOperator) -> ValueNet:
    return critic.module
