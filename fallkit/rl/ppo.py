"""PPO update (paper Table III) from TorchRL parts: GAE, ClipPPOLoss, an adaptive learning rate.

One call of `PPO.update(batch)` is one iteration's learning:

  1. GAE over the [num_envs, num_steps] batch (bootstrapping at truncation: episodes
     only end by time, so "terminated" stays False and the value of the last state
     is used).
  2. `epochs` passes over `num_minibatches` (or the trainer's: train.ppo.late_num_minibatches) shuffled
     minibatches: clipped surrogate + clipped value loss
     (+ entropy if its coefficient is not 0), gradients clipped to `max_grad_norm` (over both networks at
     once, or each by its own norm with `clip_per_network`).
  3. Before each minibatch's step, the KL between the collecting policy and the
     current one (exact, for diagonal Gaussians) adapts the learning rate as rsl_rl
     does: KL > 2·target → lr / 1.5, KL < target / 2 → lr · 1.5, within [lr_min, lr_max].
     The KL reads the policy's outputs from the loss's own forward pass (a forward hook,
     `_ActorOutputs`): the same weights and samples as a second pass would see, at no cost.
     The rule decides on the device (`fallkit.rl.optimizer`: a tensor rate, fused Adam): the update reads
     nothing back to the host; its figures are returned as device tensors. With `kl_stop`, the actor's steps
     end at the first minibatch whose KL passes kl_stop × desired_kl, its rate set to lr_min, and the critic
     steps on alone (the KL is then read on the host at every minibatch): without it, the rule takes the
     update's remaining steps at lr_min — in `train=quick`, 25 of its 40 — where the policy hardly moves.
     `actor_step_share` logs the actor's share of the steps.
  4. With `normalize_value`, the value targets join the critic's running target statistics
     first (its outputs preserved, `ValueNet.update_target_statistics`) and the value loss is
     taken in those units, so its gradients are O(1) whatever the scale of the returns.
  5. With `potential` (train.ppo.orientation_potential), GAE reads the reward shaped by
     γΦ(s') − Φ(s) (fallkit.rl.shaping); the batch's own reward stays the task's.
  6. With `mirror` (symmetric robots, fallkit.env.mirror), each minibatch is extended by its
     mirror image before the loss: mirrored policy and critic observations and actions with
     the original advantage, value target, old value and old log-probability (rsl_rl's
     symmetry augmentation), so every sample also teaches the mirrored fall. The KL above
     stays on the original samples: only they were drawn from the collecting policy.
     `mirror_loss` logs how far the policy is from symmetric (see `mirror_error`).
  7. With `value_per_term` (a decomposed critic), the critic has a value head per reward term and
     GAE runs per term on the env's ("next", "reward_terms"); the advantage is the sum of the
     terms' advantages (the task's, when the heads sum to V), the value loss covers every head
     (with `normalize_value`, each in units of its own targets' statistics; the shaping of 5.
     joins the orientation head's reward). `advantage_std/<term>` logs each term's spread.
     The env reports the impact term per component (RewardSum.columns); those columns are summed
     into the impact head, or each keeps a head of its own with `value_per_component`.
     `term_lam` and `term_gamma` give some terms a GAE λ or a discount of their own
     (fallkit.rl.value_heads): by default the orientation term, paid late and decided early, a shorter λ (config.train.DEFAULT_TERM_LAM).
  8. With `relabels` (train.ppo.relabel_sensitivity: a policy that observes its sensitivity weights;
     train.ppo.relabel_end_pose), the batch is copied under newly drawn weights, its impact repriced,
     and/or under other end poses, its tracking terms recomputed (fallkit.rl.relabel), GAE
     runs on the copy too, and each minibatch is extended by the copy's rows of the same samples:
     the same actions priced under two weightings. The copy's old log-probability is the collecting
     policy's at the copy's observation, its advantage scaled by the truncated importance weight
     (`fallkit.rl.relabel.weigh_copy`); the KL stays on the collected samples, as with the mirror, which then
     mirrors both.
  9. With `teachers` (train.teachers: a policy with sensitivity inputs and policies trained at fixed
     weights, each off the robot's in one component), each batch's samples get the teachers' mean actions blended by their
     drawn weight (fallkit.rl.teachers), and the loss gains α·Σ_j (μ_j − μ̂_j)² over the collected
     samples of each minibatch, logged as `teacher_loss`.

With torch.distributed initialised (torchrun), gradients are averaged over ranks
before each optimizer step, and the KL used for the learning rate is averaged too,
so every rank keeps identical weights and learning rate.
"""

from __future__ import annotations

import math

import torch
from tensordict import TensorDict
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value import GAE
from torchrl.objectives.value.functional import vec_generalized_advantage_estimate

from fallkit.config import PPOConfig
from fallkit.env.mirror import ObservationMirror
from fallkit.env.rewards.context import RewardSum
from fallkit.rl.mirror_samples import mirror_error, with_mirror_image
from fallkit.rl.models import GaussianPolicyNet, policy_net, value_net
from fallkit.rl.optimizer import AdaptiveAdam
from fallkit.rl.ranks import average_gradients, mean_over_ranks, merge_over_ranks
from fallkit.rl.relabel import EndPoseRelabel, SensitivityRelabel, weigh_copy
from fallkit.rl.shaping import SHAPED_REWARD, OrientationPotential
from fallkit.rl.teachers import Teachers
from fallkit.rl.value_heads import per_head, value_heads


def gaussian_kl(loc_old: torch.Tensor, scale_old: torch.Tensor, loc: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """Mean over the batch of KL(old ‖ new) for diagonal Gaussians."""
    kl = torch.log(scale / scale_old) + (scale_old.square() + (loc_old - loc).square()) / (2.0 * scale.square()) - 0.5
    return kl.sum(-1).mean()


class _ActorOutputs:
    """The (loc, scale) of the policy network's latest forward pass, detached, and its input and loc with
    their graph (for the prior penalty): a forward hook on the network the loss module calls (ClipPPOLoss
    keeps its own copy of the actor, so the hook goes there)."""

    def __init__(self, net: GaussianPolicyNet):
        self.loc = self.scale = self.obs = self.graph_loc = None
        net.register_forward_hook(self._keep)

    def _keep(self, module, inputs, outputs) -> None:
        self.obs, self.graph_loc = inputs[0], outputs[0]
        self.loc, self.scale = (t.detach() for t in outputs)


class PPO:
    def __init__(
        self,
        actor,
        critic,
        cfg: PPOConfig,
        mirror: ObservationMirror | None = None,
        potential: OrientationPotential | None = None,
        rewards: RewardSum | None = None,
        relabels: list[SensitivityRelabel | EndPoseRelabel] = (),
        teachers: Teachers | None = None,
        teachers_coef: float = 1.0,
    ):
        if cfg.mirror and mirror is None:
            raise ValueError("PPO: train.ppo.mirror needs the robot's ObservationMirror (fallkit.env.mirror)")
        if (cfg.relabel_sensitivity or cfg.relabel_end_pose) and not relabels:
            raise ValueError("PPO: train.ppo.relabel_* needs its relabelling (fallkit.rl.relabel)")
        if cfg.value_per_term and rewards is None:
            raise ValueError("PPO: train.ppo.value_per_term needs the env's reward terms (rewards=env.rewards)")
        self.cfg = cfg
        self.mirror = mirror if cfg.mirror else None
        self.potential = potential
        self.relabels = list(relabels)  # applied in turn to one copy of the batch
        self.teachers, self.teachers_coef = teachers, teachers_coef
        # with value_per_term: what each value head learns (names for the logs), and which head each of
        # the env's reward columns adds to (None: one head per column)
        self.term_names, self.column_head = value_heads(rewards, cfg) if rewards is not None else ([], None)
        head_terms = self.term_names  # each head's reward term: a head per component is its impact term's
        if rewards is not None and cfg.value_per_component:
            head_terms = [rewards.names[k] for k in rewards.column_term.tolist()]
        self.head_lam = per_head(head_terms, cfg, "term_lam")  # None: every head uses lam
        self.head_gamma = per_head(head_terms, cfg, "term_gamma")  # None: every head uses gamma
        self.actor, self.critic = actor, critic
        self.loss = ClipPPOLoss(
            actor,
            critic,
            clip_epsilon=cfg.clip,
            entropy_bonus=cfg.entropy_coef > 0,
            entropy_coeff=cfg.entropy_coef if cfg.entropy_coef > 0 else None,
            critic_coeff=cfg.value_coef,
            loss_critic_type="l2",
            normalize_advantage=True,
            clip_value=cfg.value_clip if cfg.value_clip is not None else False,
            reduction="none",  # _total_loss takes the means: a value loss per head needs its own scale first
        )
        self.gae = GAE(gamma=cfg.gamma, lmbda=cfg.lam, value_network=critic, average_gae=False)
        if potential is not None:
            self.gae.set_keys(reward=SHAPED_REWARD)
        self.params = [p for p in self.loss.parameters() if p.requires_grad]
        # two groups: the actor's rate follows the KL rule, the critic's too unless it has its own
        critic_ids = {id(p) for p in critic.parameters()}
        self.optimizer = AdaptiveAdam(
            [p for p in self.params if id(p) not in critic_ids], [p for p in self.params if id(p) in critic_ids], cfg
        )
        self.actor_outputs = _ActorOutputs(policy_net(self.loss.actor_network))
        # train.ppo.prior_coef's pull toward it; without a prior there is none to pull toward (a config with
        # train.prior=none and prior_coef > 0 is refused in one line: FallkitConfig)
        self.prior = policy_net(self.loss.actor_network).prior

    def update(
        self, batch: TensorDict, generator: torch.Generator | None = None, num_minibatches: int | None = None
    ) -> dict[str, torch.Tensor]:
        """Learn from one [num_envs, num_steps] batch in `num_minibatches` (else the config's) minibatches an epoch;
        the iteration's mean figures, scalar tensors still on the device (the trainer reads them all at once)."""
        cfg, minibatches = self.cfg, num_minibatches or self.cfg.num_minibatches
        critic_net = value_net(self.critic)
        flat, flat_image, advantage_stats = self._learning_samples(batch, critic_net, generator)
        n, mb = flat.shape[0], flat.shape[0] // minibatches
        # learning_rate_mean: the actor's rate averaged over its steps; the rule moves it at every minibatch, so
        # `learning_rate` (the rate after the last one) can sit at lr_min while most steps were taken above it
        sums, critic_loss_sum = 0.0, 0.0  # the actor's minibatches' figures and every minibatch's value loss
        grad_norms = torch.zeros(2, device=flat.device)  # actor, critic: before clipping
        count = figured = 0  # minibatches; those the actor's loss was taken on (its last one the stopping one)
        actor_stepping = True  # until train.ppo.kl_stop ends the actor's steps for this update
        # every epoch's shuffle in one copy to the device (a copy waits for the device's queue)
        perms = torch.stack([torch.randperm(n, generator=generator) for _ in range(cfg.epochs)]).to(flat.device)
        for perm in perms:
            for k in range(minibatches):
                rows = perm[k * mb : (k + 1) * mb]
                data, unmirrored = self._minibatch(flat, flat_image, rows)
                if actor_stepping:
                    loss, loss_critic, figures, actor_stepping = self._actor_and_critic_loss(
                        flat, data, rows, mb, unmirrored, critic_net
                    )
                    sums = sums + torch.stack([f.detach().to(flat.device, torch.float32) for f in figures.values()])
                    figured += 1
                else:  # the critic alone: no actor pass, the larger part of a step on a CPU
                    loss = loss_critic = _critic_loss(self.loss.loss_critic(data)[0], critic_net)

                self.optimizer.zero_grad()
                loss.backward()
                average_gradients(self.params)
                grad_norms += (norms := self._group_grad_norms())
                if cfg.clip_per_network:
                    for group, norm in zip(self.optimizer.param_groups, norms):
                        torch.nn.utils.clip_grads_with_norm_(group["params"], cfg.max_grad_norm, norm)
                else:
                    torch.nn.utils.clip_grad_norm_(self.params, cfg.max_grad_norm)
                self.optimizer.step()
                critic_loss_sum = critic_loss_sum + loss_critic.detach()
                count += 1
        stats = dict(zip(figures, sums / figured)) | advantage_stats
        stats["loss_critic"] = critic_loss_sum / count
        actor_count = figured - (not actor_stepping)  # the first minibatch's KL is 0: at least that step
        stats["actor_grad_norm"], stats["critic_grad_norm"] = grad_norms[0] / actor_count, grad_norms[1] / count
        stats["actor_step_share"] = torch.tensor(actor_count / count, device=flat.device)  # < 1 only with kl_stop
        stats["num_minibatches"] = torch.tensor(float(minibatches), device=flat.device)
        return stats | self._state_stats(policy_net(self.actor), critic_net)

    def _actor_and_critic_loss(
        self, flat: TensorDict, data: TensorDict, rows: torch.Tensor, mb: int, unmirrored: int, critic_net
    ) -> tuple[torch.Tensor, torch.Tensor, dict[str, torch.Tensor], bool]:
        """One minibatch's loss for both networks, its value loss, the figures it logs, and whether the actor
        steps on after it. The KL rule adapts the rate first; a KL past train.ppo.kl_stop × desired_kl leaves
        only the value loss to step on (this minibatch's actor step is the one the KL forbids) and ends the
        actor's steps for the update, the rate at lr_min: the steps the rule would take there move the policy
        little, and the next update starts from there as it would have."""
        cfg = self.cfg
        old_loc, old_scale = flat["loc"][rows], flat["scale"][rows]  # the collecting policy's
        out = self.loss(data)
        loss, loss_critic = _total_loss(out, critic_net)
        aid_loss, aids = self._learning_aids(flat, rows, mb, unmirrored)
        loss = loss + aid_loss
        # KL of this minibatch between the collecting policy and the current one, from the loss's forward
        # pass (the collected samples only, even with the mirror or the relabelled copy: only they were
        # drawn from the collecting policy at their inputs), before this step
        loc, scale = self.actor_outputs.loc[:mb], self.actor_outputs.scale[:mb]
        kl = mean_over_ranks(gaussian_kl(old_loc, old_scale, loc, scale))
        self.optimizer.adapt(kl)
        # the same KL on every rank (averaged above), so every rank stops at the same minibatch
        stepping = cfg.kl_stop is None or float(kl) <= cfg.kl_stop * cfg.desired_kl
        if not stepping:  # kept where the rule left it, the rate climbed to ~1e-3 and learned less an iteration
            self.optimizer.start_at(cfg.lr_min)
        figures = {
            "loss_objective": out["loss_objective"].mean(),
            "loss_entropy": out["loss_entropy"].mean() if "loss_entropy" in out.keys() else torch.zeros(()),
            "kl": kl,
            "clip_fraction": out["clip_fraction"] if "clip_fraction" in out.keys() else torch.zeros(()),
            "learning_rate_mean": self.optimizer.learning_rate,  # the rate this step was taken at
        } | aids
        return (loss if stepping else loss_critic), loss_critic, figures, stepping

    def _learning_aids(
        self, flat: TensorDict, rows: torch.Tensor, mb: int, unmirrored: int
    ) -> tuple[torch.Tensor | float, dict[str, torch.Tensor]]:
        """The loss terms beside PPO's own for one minibatch (its collected samples are the loss's first `mb`
        inputs, the mirror image starts at `unmirrored`), and what each logs: train.ppo.prior_coef's pull toward
        the prior (`prior_deviation`, logged at β 0 too), the mirror's asymmetry (`mirror_loss`, logged only)
        and train.teachers' imitation of the teachers' blend (`teacher_loss`)."""
        deviation = self._prior_deviation(mb)
        loss = self.cfg.prior_coef * deviation if self.cfg.prior_coef > 0 else 0.0
        logged = {"prior_deviation": deviation}
        if self.mirror is not None:
            outputs = self.actor_outputs.loc
            logged["mirror_loss"] = mirror_error(self.mirror, outputs[:unmirrored], outputs[unmirrored:])
        if self.teachers is not None:
            imitation = (self.actor_outputs.graph_loc[:mb] - flat["teacher_loc"][rows]).square().sum(-1).mean()
            loss = loss + self.teachers_coef * imitation
            logged["teacher_loss"] = imitation
        return loss, logged

    def _prior_deviation(self, rows: int) -> torch.Tensor:
        """Σ_j d_j² of the learned deviation d = mean − prior, averaged over the loss's first `rows` inputs (the
        collected samples), with its graph: train.ppo.prior_coef's penalty, logged as `prior_deviation`."""
        if self.prior is None:
            return torch.zeros((), device=self.actor_outputs.loc.device)
        obs = self.actor_outputs.obs[:rows]
        return (self.actor_outputs.graph_loc[:rows] - self.prior(obs)).square().sum(-1).mean()

    def _learning_samples(
        self, batch: TensorDict, critic_net, generator: torch.Generator | None
    ) -> tuple[TensorDict, TensorDict | None, dict[str, torch.Tensor]]:
        """The batch's samples with advantages and value targets, flat, holding only what the loss and
        the KL read (gathering the whole batch per minibatch was 8 % of an update); the same for its
        copy under other sensitivity weights or end poses (train.ppo.relabel_*; else None); the
        advantages' spread per term. The value targets join the critic's target statistics first."""
        keys = self.loss.tensor_keys
        advantage_stats = self.advantages(batch)
        image = None
        if self.relabels:
            image = batch
            for relabel in self.relabels:
                image = relabel(image, generator)
            self.advantages(image)
            weigh_copy(self.actor, batch, image, self.loss.tensor_keys)
        if critic_net.target is not None:
            targets = batch[keys.value_target]
            if image is not None:
                targets = torch.cat([targets, image[keys.value_target]])
            critic_net.update_target_statistics(targets, merge=merge_over_ranks)
        read = ["policy", "critic", "loc", "scale", keys.action, keys.sample_log_prob, keys.advantage, keys.value_target]
        flat = batch.select(*read, keys.value, strict=False).reshape(-1)
        flat_image = image.select(*read, keys.value, strict=False).reshape(-1) if image is not None else None
        if self.teachers is not None:  # frozen teachers, fixed observations: their targets once per batch
            flat.set("teacher_loc", self.teachers.targets(flat["policy"]))
        return flat, flat_image, advantage_stats

    def _minibatch(self, flat: TensorDict, flat_image: TensorDict | None, rows: torch.Tensor) -> tuple[TensorDict, int]:
        """The samples `rows`, then their relabelled copies (if any), then the mirror image of both (if
        any); and how many rows come before the mirror image."""
        data = flat[rows]
        if flat_image is not None:
            data = torch.cat([data, flat_image[rows]], dim=0)
        unmirrored = data.shape[0]
        if self.mirror is not None:
            data = with_mirror_image(self.mirror, data, self.loss.tensor_keys)
        return data, unmirrored

    @torch.no_grad()
    def advantages(self, batch: TensorDict) -> dict[str, torch.Tensor]:
        """GAE into the batch (advantage, value target); with a value per term, each term's advantage spread."""
        if self.potential is not None:
            # the shaping joins the orientation head, so it discounts as that head does (policy invariance)
            self.potential.shape(batch, self.cfg.term_gamma.get("orientation", self.cfg.gamma))
        if not self.cfg.value_per_term:
            self.gae(batch)
            return {}
        stds = self._gae_per_term(batch).flatten(0, -2).std(dim=0)
        return {f"advantage_std/{name}": v for name, v in zip(self.term_names, stds)}

    @torch.no_grad()
    def _gae_per_term(self, batch: TensorDict) -> torch.Tensor:
        """GAE of every reward term against its own value head (the critic's [N, T, K] output): sets the
        summed advantage [N, T, 1] and the per-term value targets [N, T, K]; returns the terms' advantages."""
        keys = self.loss.tensor_keys
        self.critic(batch)
        self.critic(batch["next"])
        terms = batch["next", "reward_terms"]
        if self.column_head is not None:  # the impact per component summed back into its term's head
            self.column_head = self.column_head.to(terms.device)  # once onto the batch's device
            terms = terms.new_zeros(*terms.shape[:-1], len(self.term_names)).index_add_(-1, self.column_head, terms)
        if self.potential is not None:  # the shaping γΦ(s') − Φ(s) is the orientation head's to learn
            shaping = batch["next", SHAPED_REWARD] - batch["next", "reward"]
            column = self.term_names.index("orientation") if "orientation" in self.term_names else 0
            terms = terms.clone()
            terms[..., column] += shaping.squeeze(-1)
        if self.head_lam is not None:
            self.head_lam = self.head_lam.to(terms)  # once onto the batch's device
        if self.head_gamma is not None:
            self.head_gamma = self.head_gamma.to(terms)
        advantages, targets = vec_generalized_advantage_estimate(
            self.cfg.gamma if self.head_gamma is None else self.head_gamma,  # a [K] γ or λ broadcasts over the heads
            self.cfg.lam if self.head_lam is None else self.head_lam,
            batch[keys.value],
            batch["next", keys.value],
            terms,
            batch["next", "done"].expand_as(terms),  # an episode's end ends every term's sum
            batch["next", "terminated"].expand_as(terms),
            time_dim=-2,
        )
        batch.set(keys.advantage, advantages.sum(dim=-1, keepdim=True))
        batch.set(keys.value_target, targets)
        batch.set("term_advantages", advantages)  # [N, T, K]: what train.level_replay.score may read
        return advantages

    @torch.no_grad()
    def _state_stats(self, net: GaussianPolicyNet, critic_net) -> dict[str, torch.Tensor]:
        """What the update leaves: learning rate, the policy's std and entropy, the value targets' statistics."""
        stats = {"learning_rate": self.optimizer.learning_rate.clone(), "action_std": net.log_std.exp().mean()}
        # entropy of the diagonal Gaussian policy (state-independent): Σ_j ½·log(2πe) + log σ_j
        stats["entropy"] = 0.5 * math.log(2.0 * math.pi * math.e) * net.log_std.numel() + net.log_std.sum()
        if critic_net.target is not None:  # per value head: the whole return's, or each term's
            heads = [f"/{name}" for name in self.term_names] if critic_net.target.mean.numel() > 1 else [""]
            for head, mean, std in zip(heads, critic_net.target.mean.clone(), critic_net.target_std()):
                stats[f"value_target_mean{head}"], stats[f"value_target_std{head}"] = mean, std
        return stats

    def _group_grad_norms(self) -> torch.Tensor:
        """[actor, critic] gradient norms before clipping: with one clip over both, a critic whose
        gradients dwarf the actor's shrinks the actor's step too — these say when it does."""
        grads = [[p.grad for p in group["params"] if p.grad is not None] for group in self.optimizer.param_groups]
        return torch.stack([torch.nn.utils.get_total_norm(g) for g in grads])

    def state_dict(self) -> dict:
        return self.optimizer.state_dict()

    def load_state_dict(self, state: dict) -> None:
        self.optimizer.load_state_dict(state)


def _total_loss(out: TensorDict, critic_net) -> tuple[torch.Tensor, torch.Tensor]:
    """(surrogate + value loss + entropy term, the value loss), each the mean of the loss module's
    per-sample terms: the value loss in units of the value targets' statistics where the critic
    normalises them (train.ppo.normalize_value), each value head's in its own."""
    loss_critic = _critic_loss(out["loss_critic"], critic_net)
    loss = out["loss_objective"].mean() + loss_critic
    if "loss_entropy" in out.keys():
        loss = loss + out["loss_entropy"].mean()
    return loss, loss_critic


def _critic_loss(per_sample: torch.Tensor, critic_net) -> torch.Tensor:
    """The mean of the loss module's per-sample value losses, each value head's in units of its own targets'
    statistics where the critic normalises them (train.ppo.normalize_value)."""
    if critic_net.target is not None:
        per_sample = per_sample / critic_net.target_std().square()
    return per_sample.mean()
