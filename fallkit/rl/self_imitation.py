"""train.self_imitation: imitate the policy's own past actions that turned out better than the critic expected.

Why: an oracle over 34 trained policies' results on the same 256 evaluation falls lands them at an MROE
of 0.48 rad, each policy alone at 1.38-1.60 (docs/training.md): exploration does find landings that
steer a fall right, but PPO uses each sample for one update's few epochs, clipped, and then forgets it.
Self-imitation learning (SIL, Oh et al. 2018) keeps the steps whose discounted return R turned out
above the critic's value V(s) and, after each PPO update, raises their log-probability in proportion
to (R − V(s))₊: a lucky push that turned a fall onto the right side is learned again until the
critic expects it. Steps at or below V(s) add nothing, so SIL can only pull toward the better
outcomes the policy itself reached (its lower-bound argument).

How, in the trainer's loop:
  add(batch)   per world, the steps of the running episode (the raw policy and critic observations, the
               action, the task reward); when the episode ends its returns R_t = Σ_k γ^(k−t) r_k, the
               tail bootstrapped by V at the last next-state as GAE does (episodes end by time), and
               the steps with R_t > V(s_t) go into a first-in-first-out store.
  update()     `steps` minibatches from the store: loss = mean(−log π(a|s) · min((R − V(s))₊ / σ_A,
               max_weight)), V read now (a step the critic has come to expect stops pulling), σ_A the
               latest PPO batch's advantage std (so the weights have PPO's normalised scale); an Adam of
               its own on the actor's parameters, gradients clipped to 1. Adam divides out a constant
               factor of the loss, so `learning_rate` and `steps` set its strength, not a coefficient.
With `term` (a reward term, e.g. orientation) R and V are that term's return and value head: the actions
that steered better than expected, whatever they cost in impact (PPO's own update still prices that).
Only the actor learns here (SIL's value term is left out: the critic's heads learn per reward term in
PPO). Off by default (`steps=0`); measured in docs/training.md.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict

from fallkit.config import FallkitConfig, SelfImitationConfig
from fallkit.env.rewards.context import RewardSum
from fallkit.errors import ConfigError
from fallkit.rl.models import policy_net, value_net


def make_self_imitation(
    config: FallkitConfig, actor, critic, rewards: RewardSum, heads: list[str], num_envs: int, max_steps: int
) -> SelfImitation | None:
    """The run's self-imitation (None when train.self_imitation.steps is 0), its `term` checked either way:
    the reward columns and the value head of a term (`heads`: the critic's, fallkit.rl.value_heads.critic_heads)."""
    cfg, ppo = config.train.self_imitation, config.train.ppo
    columns = head = None
    if cfg.term != "return":
        if cfg.term not in heads or ppo.value_per_component:
            raise ConfigError(
                f"train.self_imitation.term={cfg.term} is not a reward term with a value head of its own (heads: "
                f"{', '.join(heads)}): use 'return', or a reward term with train.ppo.value_per_term=true "
                "(and value_per_component=false)"
            )
        columns = (rewards.column_term == rewards.names.index(cfg.term)).nonzero().view(-1)
        head = heads.index(cfg.term)
    if cfg.steps == 0:
        return None
    gamma = ppo.term_gamma.get(cfg.term, ppo.gamma)
    return SelfImitation(cfg, actor, critic, num_envs, max_steps, gamma, columns, head)


class SelfImitation:
    def __init__(
        self,
        cfg: SelfImitationConfig,
        actor,
        critic,
        num_envs: int,
        max_steps: int,
        gamma: float,
        columns: torch.Tensor | None = None,
        head: int | None = None,
    ):
        self.cfg, self.gamma = cfg, gamma
        self.columns, self.head = columns, head  # one term's reward columns and value head; None: the whole return
        self.net, self.value = policy_net(actor), value_net(critic)
        self.optimizer = torch.optim.Adam(self.net.parameters(), lr=cfg.learning_rate)
        self.num_envs, self.max_steps = num_envs, max_steps
        self.episode: dict[str, torch.Tensor] = {}  # per world [N, max_steps, ...], built on the first batch
        self.length = torch.zeros(num_envs, dtype=torch.long)  # steps of each world's running episode so far
        self.store: dict[str, torch.Tensor] = {}  # [size, ...]
        self.stored, self.next_slot = 0, 0  # filled rows; where the next row goes
        self.advantage_std = torch.ones(())
        self.added = torch.zeros(())  # steps that entered the store this iteration (a logged figure)

    # ---- collecting ---------------------------------------------------------------------------

    @torch.no_grad()
    def add(self, batch: TensorDict) -> None:
        """The [N, T] batch's steps into the running episodes; the finished episodes' better-than-expected
        steps into the store."""
        if not self.episode:
            self._allocate(batch)
        self.length = self.length.to(batch.device)
        self.added = torch.zeros((), device=batch.device)
        if "advantage" in batch.keys():
            self.advantage_std = batch["advantage"].std().clamp(min=1e-6)
        done = batch["next", "done"].view(self.num_envs, -1)
        worlds = torch.arange(self.num_envs, device=batch.device)
        for t in range(done.shape[1]):
            # an episode longer than the buffer (none in a FallEnv: its episodes end by max_steps) keeps its last
            slot = self.length.clamp(max=self.max_steps - 1)
            for key, value in self._step(batch, t).items():
                self.episode[key][worlds, slot] = value
            self.length = (slot + 1).clamp(max=self.max_steps)
            ended = done[:, t].nonzero().view(-1)
            if ended.numel():
                self._finish(ended, batch["next", "critic"][ended, t])
                self.length[ended] = 0

    def _step(self, batch: TensorDict, t: int) -> dict[str, torch.Tensor]:
        if self.columns is None:
            reward = batch["next", "reward"][:, t, 0]
        else:
            self.columns = self.columns.to(batch.device)
            reward = batch["next", "reward_terms"][:, t].index_select(-1, self.columns).sum(-1)
        step = {key: batch[key][:, t] for key in ("policy", "critic", "action")}
        return step | {"reward": reward}

    def _allocate(self, batch: TensorDict) -> None:
        shape = (self.num_envs, self.max_steps)
        for key, value in self._step(batch, 0).items():
            self.episode[key] = value.new_zeros(*shape, *value.shape[1:])
            self.store[key] = value.new_zeros(self.cfg.size, *value.shape[1:])
        self.store["return"] = self.store.pop("reward")

    def _finish(self, worlds: torch.Tensor, last_next_critic: torch.Tensor) -> None:
        """Returns of the episodes that ended in `worlds`; their steps with R > V(s) into the store."""
        length = self.length[worlds]  # [n]
        steps = torch.arange(self.max_steps, device=length.device)
        valid = steps < length.unsqueeze(-1)  # [n, L]
        reward = self.episode["reward"][worlds] * valid
        # R_t = Σ_{k ≥ t} γ^(k−t) r_k + γ^(len−t) V(s_len): one product with the upper-triangular discounts
        power = (steps.unsqueeze(0) - steps.unsqueeze(1)).to(reward.dtype)  # [t, k] = k − t
        discounts = torch.where(power >= 0, self.gamma**power.clamp(min=0), torch.zeros_like(power))
        tail = self.gamma ** (length.unsqueeze(-1) - steps).clamp(min=0).to(reward.dtype)
        returns = reward @ discounts.T + tail * self._value(last_next_critic).unsqueeze(-1)
        margin = self.cfg.min_weight * self.advantage_std  # 0: every step that beat V
        keep = valid & (returns - self._value(self.episode["critic"][worlds]) > margin)
        rows = {key: self.episode[key][worlds][keep] for key in ("policy", "critic", "action")}
        rows["return"] = returns[keep]
        self._push(rows)

    def _value(self, critic_obs: torch.Tensor) -> torch.Tensor:
        """V(s): the sum of the critic's heads, or the term's head."""
        value = self.value(critic_obs)
        return value.sum(-1) if self.head is None else value[..., self.head]

    def _push(self, rows: dict[str, torch.Tensor]) -> None:
        n = rows["return"].shape[0]
        if n == 0:
            return
        if n > self.cfg.size:  # more than the whole store: the latest steps
            rows, n = {k: v[-self.cfg.size :] for k, v in rows.items()}, self.cfg.size
        index = (self.next_slot + torch.arange(n, device=rows["return"].device)) % self.cfg.size
        for key, value in rows.items():
            self.store[key][index] = value
        self.next_slot = (self.next_slot + n) % self.cfg.size
        self.stored = min(self.stored + n, self.cfg.size)
        self.added = self.added + n

    # ---- learning -----------------------------------------------------------------------------

    def update(self, generator: torch.Generator | None = None) -> dict[str, torch.Tensor]:
        """`steps` minibatches of the self-imitation loss on the actor; the iteration's figures."""
        device = self.advantage_std.device
        stored = torch.tensor(float(self.stored), device=device)
        figures = {"self_imitation/stored": stored, "self_imitation/added": self.added}
        cfg, zero = self.cfg, torch.zeros((), device=device)
        loss_sum, weight_sum, pulling = zero, zero, zero  # the same columns from the first iteration on (metrics.csv)
        for _ in range(cfg.steps if self.stored >= cfg.minibatch else 0):
            rows = torch.randint(self.stored, (cfg.minibatch,), generator=generator).to(device)
            with torch.no_grad():
                gap = self.store["return"][rows] - self._value(self.store["critic"][rows])
                weight = (gap.clamp(min=0) / self.advantage_std).clamp(max=cfg.max_weight)
            loc, scale = self.net(self.store["policy"][rows])
            log_prob = torch.distributions.Normal(loc, scale).log_prob(self.store["action"][rows]).sum(-1)
            loss = -(log_prob * weight).mean()
            self.optimizer.zero_grad()
            loss.backward()
            torch.nn.utils.clip_grad_norm_(self.net.parameters(), 1.0)
            self.optimizer.step()
            loss_sum = loss_sum + loss.detach()
            weight_sum = weight_sum + weight.mean()
            pulling = pulling + (gap > 0).float().mean()
        figures["self_imitation/loss"] = loss_sum / cfg.steps
        figures["self_imitation/weight"] = weight_sum / cfg.steps  # mean (R − V)₊ / σ_A of the sampled steps
        figures["self_imitation/pulling"] = pulling / cfg.steps  # share of them still above V(s)
        return figures

    # ---- checkpoints ----------------------------------------------------------------------------

    def state_dict(self) -> dict:
        return {
            "episode": dict(self.episode), "length": self.length, "store": dict(self.store), "stored": self.stored,
            "next_slot": self.next_slot, "advantage_std": self.advantage_std, "optimizer": self.optimizer.state_dict(),
        }  # fmt: skip

    def load_state_dict(self, state: dict) -> None:
        self.episode, self.store = dict(state["episode"]), dict(state["store"])
        self.length, self.advantage_std = state["length"], state["advantage_std"]
        self.stored, self.next_slot = int(state["stored"]), int(state["next_slot"])
        self.optimizer.load_state_dict(state["optimizer"])
