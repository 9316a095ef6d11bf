"""Hindsight relabelling: every collected fall also teaches the same fall under other sensitivity weights
(`SensitivityRelabel`) or another end pose (`EndPoseRelabel`).

With env.sensitivity_inputs a policy must learn what the weights it observes ask of it, from
episodes that each show one draw of the weights, and at these budgets it barely does
(docs/sensitivity_inputs.md: the head at 4x moves its p95 max force ~5 %). Yet the weights change
nothing in the physics: they only price the contact forces, and the environment reports each
component's priced peak as a reward column of its own, weight·dt·(−(w_c ‖f_c‖∞)²). So a collected
rollout is as well a rollout under any other weights w': the same states and actions, ln w' in the
observations, each component's impact column times (w'_c / w_c)². `SensitivityRelabel` makes that
copy, w' drawn per world as the env draws an episode's weights (`SensitivityDraw`), one draw for
the world's whole rollout; PPO (`train.ppo.relabel_sensitivity`) runs GAE on it with the critic
reading w' and trains on both, so every minibatch holds the same actions priced two ways: the
contrast that says what a weight input means.

The copy's actions were drawn by the policy at w, not at w'. PPO (`weigh_copy`) takes
the collecting policy's log-probability at the copy's observation as the copy's old one, so the ratio
π_θ(a | o') / π_old(a | o') starts at 1, and scales the copy's advantage by the truncated importance
weight min(1, π_old(a | o') / π_old(a | o)) of an action drawn at o (V-trace's ρ̄; hindsight policy
gradients weigh relabelled goals alike, Rauber et al. 2019). The later actions of the rollout are the
policy's at w too; that stays uncorrected, as PPO leaves the epochs' reuse of a batch uncorrected.
"""

from __future__ import annotations

from types import SimpleNamespace

import torch
from tensordict import TensorDictBase
from torchrl.modules import ProbabilisticActor

from fallkit.config.env import SensitivityInputs
from fallkit.env.observations import actor_slices, sensitivity_input
from fallkit.env.randomization import SensitivityDraw
from fallkit.env.rewards.context import RewardSum
from fallkit.env.rewards.impact import impact
from fallkit.env.rewards.tracking import blend, joints, orientation
from fallkit.errors import ConfigError
from fallkit.robots.spec import RobotSpec
from fallkit.rotations import gravity_in_frame

OBSERVATIONS = ("policy", "critic", ("next", "policy"), ("next", "critic"))  # what a copy relabels
# A relabelled copy's importance weight min(1, π_old(a|o')/π_old(a|o)) below which it gets no advantage
# (`weigh_copy`): the action is then far off the collecting policy at o'.
RELABEL_MIN_WEIGHT = 0.05
SILENT = 30.0  # [nats] such a copy's old log-probability above its current one: no gradient from its ratio


class SensitivityRelabel:
    """Copies of collected rollouts under newly drawn sensitivity weights (see the module's docstring).

    The critic observation starts with the actor's (fallkit.env.observations), so ln w sits in the
    same columns of both. Weights are read back from the observation (ln w), so a weight below
    MIN_SENSITIVITY is priced as the policy observed it.
    """

    def __init__(self, spec: RobotSpec, inputs: SensitivityInputs, rewards: RewardSum, gravity: bool = False):
        if not inputs.enabled or inputs.low == inputs.high:
            raise ConfigError(
                "train.ppo.relabel_sensitivity draws other sensitivity weights for the collected falls: it needs "
                "env.sensitivity_inputs.enabled=true with low < high"
            )
        if "impact" not in rewards.names or rewards.functions[rewards.names.index("impact")] is not impact:
            raise ConfigError(
                "train.ppo.relabel_sensitivity reprices the built-in impact term, −(w_c ‖f_c‖∞)² per component; "
                "this run's reward has no such term (reward.impact=0 or reward.terms.impact replaced): switch it off"
            )
        self.draw = SensitivityDraw(inputs, spec)  # on the CPU
        self.columns = actor_slices(spec, sensitivity=True, gravity=gravity)["sensitivity"]
        term = rewards.names.index("impact")
        self.impact_columns = torch.nonzero(rewards.column_term.cpu() == term).squeeze(-1)  # [C], component order

    def __call__(self, batch: TensorDictBase, generator: torch.Generator | None = None) -> TensorDictBase:
        """The copy of an [N, T] batch (holding "policy", "critic", ("next", "critic") and ("next",
        "reward_terms"); every other key as it is) under weights drawn per world."""
        observed = batch["policy"][..., self.columns]  # [N, T, C]: ln w of each step's episode
        device = observed.device
        drawn = self.draw(batch.shape[0], generator)  # [N, C]
        new = sensitivity_input(drawn).to(device).unsqueeze(1)  # [N, 1, C]: ln w', the world's whole rollout
        price = torch.exp(2.0 * (new - observed))  # (w' / w)² per step and component
        terms = batch["next", "reward_terms"].clone()
        terms[..., self.impact_columns.to(device)] *= price
        image = batch.clone(recurse=False)
        for key in OBSERVATIONS:
            if key in batch.keys(include_nested=True):
                image.set(key, _with_columns(batch[key], self.columns, new))
        image.set(("next", "reward_terms"), terms)
        image.set(("next", "reward"), terms.sum(dim=-1, keepdim=True))
        return image


class EndPoseRelabel:
    """Copies of collected rollouts under other end poses, one drawn per world from the training set.

    The end pose changes nothing in the physics either: it enters the observations (the target tilt in
    the path frame, the target joints, with env.observe_gravity the target's up axis) and two reward
    terms, orientation −u(t)‖R(θ)ᵀe_z − R(θ̂)ᵀe_z‖² and joints −u(t)‖q − q̂‖², both functions of the state
    the step reached, which the critic observation holds without noise (its actor part: the root's tilt
    in the path frame, whose up axis is the world-frame root's, and the joints; its phase t/T gives u(t)).
    So the copy recomputes those two columns with the drawn end pose, through the reward's own term
    functions, and keeps every other column. A fall that ended on its back teaches, priced for an end
    pose on the back, what reached it. PPO weighs the copy as it weighs any relabelled one
    (`weigh_copy`).
    """

    def __init__(
        self, spec: RobotSpec, goal_tilt: torch.Tensor, goal_joints: torch.Tensor, rewards: RewardSum,
        episode_seconds: float, blend_time: float, sensitivity: bool = False, gravity: bool = False,
    ):  # fmt: skip
        for name, term in (("orientation", orientation), ("joints", joints)):
            if name in rewards.names and rewards.functions[rewards.names.index(name)] is not term:
                raise ConfigError(
                    f"train.ppo.relabel_end_pose recomputes the built-in {name} term for other end poses; this run's "
                    f"reward.terms.{name} replaces it: switch relabelling off"
                )
        self.goal_tilt, self.goal_joints = goal_tilt.float().cpu(), goal_joints.float().cpu()  # [P, 4], [P, J]
        self.cols = actor_slices(spec, sensitivity, gravity)
        self.phase = sum(c.stop - c.start for c in self.cols.values())  # the critic's first privileged column
        self.episode_seconds, self.blend_time = episode_seconds, blend_time  # phase t/T back to t
        self.recomputed = [(rewards.columns.index(n), f) for n, f in (("orientation", orientation), ("joints", joints))
                           if n in rewards.columns]  # fmt: skip
        self.rewards = rewards  # its scale read at each call: train.early_reward_factor changes it

    def __call__(self, batch: TensorDictBase, generator: torch.Generator | None = None) -> TensorDictBase:
        """The copy of an [N, T] batch (as `SensitivityRelabel`'s) under end poses drawn per world."""
        device = batch.device
        ids = torch.randint(len(self.goal_tilt), (batch.shape[0],), generator=generator)
        tilt, q = (t[ids].to(device).unsqueeze(1) for t in (self.goal_tilt, self.goal_joints))  # [N, 1, ·]
        goal = {"goal_root_quat": tilt, "goal_joint_pos": q, "goal_gravity": gravity_in_frame(tilt)}
        image = batch.clone(recurse=False)
        for key in OBSERVATIONS:
            if key in batch.keys(include_nested=True):
                obs = batch[key]
                for name, values in goal.items():
                    if name in self.cols:
                        obs = _with_columns(obs, self.cols[name], values)
                image.set(key, obs)
        reached = batch["next", "critic"]  # the state each step reached, noiseless
        time = reached[..., self.phase] * self.episode_seconds
        ctx = SimpleNamespace(
            state=SimpleNamespace(root_quat=reached[..., self.cols["root_quat"]], joint_pos=reached[..., self.cols["joint_pos"]]),
            target_root_quat=tilt, target_joint_pos=q, blend=blend(time, self.blend_time),
        )  # fmt: skip
        terms = batch["next", "reward_terms"].clone()
        for column, term in self.recomputed:
            terms[..., column] = self.rewards.scale[column].to(device) * term(ctx)
        image.set(("next", "reward_terms"), terms)
        image.set(("next", "reward"), terms.sum(dim=-1, keepdim=True))
        return image


def _with_columns(obs: torch.Tensor, columns: slice, values: torch.Tensor) -> torch.Tensor:
    out = obs.clone()
    out[..., columns] = values.expand(*obs.shape[:-1], values.shape[-1])
    return out


@torch.no_grad()
def weigh_copy(actor: ProbabilisticActor, batch: TensorDictBase, image: TensorDictBase, keys) -> None:
    """How PPO weighs a relabelled copy `image` of `batch` (`keys`: the loss's tensor keys), in place.

    The copy's old log-probability becomes the collecting policy's at the copy's own observation o',
    so PPO's ratio starts at 1 there; the copy's advantage is scaled by the truncated importance weight
    min(1, π_old(a|o') / π_old(a|o)) of an action drawn at o (V-trace's ρ̄).

    Keeping π_old(a|o) as the copy's old log-probability (the first form) made the ratio start at
    π(a|o')/π_old(a|o): for a policy that reads its weights, far from 1, and outside the clip band
    the only gradients left (r < 1 − ε with A > 0, r > 1 + ε with A < 0) move π(a|o') back toward
    π_old(a|o) — training the policy to ignore its weight inputs (measured: docs/sensitivity_inputs.md).

    A copy whose action the collecting policy would hardly have drawn at o' (weight below
    `RELABEL_MIN_WEIGHT`) keeps its value target but teaches the actor nothing: with π_old(a|o') tiny,
    a small step of the policy makes its ratio huge, and PPO's clip does not bound the surrogate of a
    huge ratio with a negative advantage (measured: end-pose copies, whose goal moves the action far
    more than a weight does, drove the surrogate to 1e7 and the weights to NaN within 200
    iterations). Its old log-probability is set `SILENT` nats above the current one: a ratio of
    e^−30, so the surrogate gives it no gradient whatever its advantage after the minibatch's
    normalisation (a zero advantage would not stay zero there)."""
    log_prob = actor.get_dist(image.select("policy")).log_prob(image[keys.action])
    weight = (log_prob - batch[keys.sample_log_prob]).exp().clamp(max=1.0)
    silent = weight < RELABEL_MIN_WEIGHT
    image.set(keys.sample_log_prob, torch.where(silent, log_prob + SILENT, log_prob))
    image.set(keys.advantage, image[keys.advantage] * torch.where(silent, 0.0, weight).unsqueeze(-1))
