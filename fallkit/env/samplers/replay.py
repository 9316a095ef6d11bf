"""Prioritised replay of training falls (Prioritized Level Replay, Jiang, Grefenstette & Rocktäschel 2021).

The paper draws every training episode afresh: an initial state from Table II's ranges and an end
pose from the training split. Most of those falls teach the actor little once the critic knows
them: a fall that ends on the wrong side whatever the actor does, or one the prior lands anyway,
has small advantages at every step. The falls whose outcome the actor's noise still flips — the
ones where steering is learnt — have large ones. With `train.level_replay.share = p`, a share p of
the restarting worlds replay a stored fall instead (its initial state and end pose; the disturbances,
randomisation and drawn weights are drawn afresh), chosen by its score: the mean |advantage| over
its last play (PLR's L1 value loss, the advantage the actor learns from). The rest start fresh
falls, which join the buffer when they score above its lowest. Ranks of the scores set the chance
of a replay, (1/rank)^(1/temperature), mixed with a share for the falls played longest ago
(staleness, so old scores are renewed). A stored fall replays in one world at a time. Evaluation
is untouched: it resets its worlds to its own falls (`FallEnv.reset_to`).

Each play of a fall (an episode) has an id, the env's "fall_id" key at every step; the trainer
hands the batch's ids and advantages to `record` after each update, and a play is scored once its
last steps have been recorded.
"""

from __future__ import annotations

import torch

from fallkit.config import LevelReplayConfig

_F64 = torch.float64


class LevelReplay:
    """The stored falls, their scores, and which play each world is in (see the module docstring)."""

    def __init__(self, config: LevelReplayConfig, num_worlds: int, nq: int, nv: int, device: torch.device | str):
        k, n = config.size, num_worlds
        self.config, self.device = config, torch.device(device)
        self.qpos, self.qvel = torch.zeros(k, nq, dtype=_F64), torch.zeros(k, nv, dtype=_F64)
        self.pose = torch.zeros(k, dtype=torch.long)
        self.score = torch.zeros(k, dtype=_F64)
        self.last_played = torch.zeros(k, dtype=torch.long)  # episodes started when it last started
        self.busy = torch.zeros(k, dtype=torch.bool)  # being played, or played and not yet scored
        self.filled, self.started, self.replayed = 0, 0, 0
        # each world's play: its id, stored slot (-1: a fresh fall), the fall, the |advantage| summed so far
        self.play = torch.full((n,), -1, dtype=torch.long)
        self.fall_id = self.play.to(self.device)  # the env's "fall_id" key
        self.slot = torch.full((n,), -1, dtype=torch.long)
        self.world_qpos, self.world_qvel = torch.zeros(n, nq, dtype=_F64), torch.zeros(n, nv, dtype=_F64)
        self.world_pose = torch.zeros(n, dtype=torch.long)
        self.sum, self.count = torch.zeros(n, dtype=_F64), torch.zeros(n, dtype=_F64)
        self.ended: list[dict[str, torch.Tensor]] = []  # plays ended since the last record, not yet scored

    def restart(
        self, ids: torch.Tensor, qpos: torch.Tensor, qvel: torch.Tensor, poses: torch.Tensor, generator: torch.Generator
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Worlds `ids` start new plays: fresh falls (qpos [n, nq], qvel [n, nv] on the CPU, poses [n]), a share
        of them replaced by stored ones. Returns the falls to start."""
        w = ids.cpu()
        live = self.play[w] >= 0
        if live.any():
            self._end(w[live])
        n = w.numel()
        replay = torch.rand(n, generator=generator) < self.config.share
        slots = self._draw(int(replay.sum()), generator) if self.filled == self.config.size else self.pose[:0]
        replay[replay.nonzero().view(-1)[slots.numel() :]] = False  # more asked than free: the rest start fresh
        qpos, qvel, poses = qpos.clone(), qvel.clone(), poses.clone()
        qpos[replay], qvel[replay] = self.qpos[slots], self.qvel[slots]
        poses[replay.to(poses.device)] = self.pose[slots].to(poses.device)
        self.busy[slots], self.last_played[slots] = True, self.started
        self.slot[w] = torch.full((n,), -1, dtype=torch.long).masked_scatter_(replay, slots)
        self.world_qpos[w], self.world_qvel[w], self.world_pose[w] = qpos, qvel, poses.cpu()
        self.sum[w], self.count[w] = 0.0, 0.0
        self.play[w] = torch.arange(self.started, self.started + n)
        self.fall_id[ids.to(self.device)] = self.play[w].to(self.device)
        self.started, self.replayed = self.started + n, self.replayed + slots.numel()
        return qpos, qvel, poses

    def record(self, fall_id: torch.Tensor, advantage: torch.Tensor) -> dict[str, torch.Tensor]:
        """A batch's [N, T] play ids and advantages (after the update that computed them): each step's
        |advantage| to its play; plays that ended before this batch's last step are then scored. Returns
        `stats()`."""
        ids, a = fall_id.reshape(fall_id.shape[0], -1).cpu(), advantage.reshape(fall_id.shape[0], -1).abs().cpu()
        current = ids == self.play.view(-1, 1)
        self.sum += torch.where(current, a, 0.0).sum(1, dtype=_F64)
        self.count += current.sum(1)
        if not self.ended:
            return self.stats()
        ended = {key: torch.cat([e[key] for e in self.ended]) for key in self.ended[0]}
        self.ended.clear()
        order = ended["play"].argsort()
        at = order[torch.searchsorted(ended["play"][order], ids[~current]).clamp_(max=order.numel() - 1)]
        found = ended["play"][at] == ids[~current]  # always, unless a batch holds a play from before a resume
        ended["sum"].index_add_(0, at[found], a[~current][found].to(_F64))
        ended["count"].index_add_(0, at[found], torch.ones(int(found.sum()), dtype=_F64))
        self._score(ended)
        return self.stats()

    def stats(self) -> dict[str, torch.Tensor]:
        """For metrics.csv: falls stored, their mean score, the share of the episodes so far that were replays."""
        mean = float(self.score[: self.filled].mean()) if self.filled else 0.0
        figures = {"stored": self.filled, "score_mean": mean, "replayed": self.replayed / max(self.started, 1)}
        return {f"level_replay/{k}": torch.tensor(float(v), device=self.device) for k, v in figures.items()}

    def state_dict(self) -> dict:
        state = {k: v.clone() for k, v in vars(self).items() if isinstance(v, torch.Tensor)}
        return state | {"counters": (self.filled, self.started, self.replayed), "ended": list(self.ended)}

    def load_state_dict(self, state: dict) -> None:
        for key, value in state.items():
            if isinstance(value, torch.Tensor):
                getattr(self, key).copy_(value)
        self.filled, self.started, self.replayed = state["counters"]
        self.ended = list(state["ended"])

    # ---- internals ----------------------------------------------------------------

    def _end(self, worlds: torch.Tensor) -> None:
        """The plays of `worlds` end: kept, with what they have summed, until their last steps are recorded."""
        self.ended.append({
            "play": self.play[worlds].clone(), "slot": self.slot[worlds].clone(), "qpos": self.world_qpos[worlds],
            "qvel": self.world_qvel[worlds], "pose": self.world_pose[worlds], "sum": self.sum[worlds].clone(),
            "count": self.count[worlds].clone(),
        })  # fmt: skip

    def _score(self, ended: dict[str, torch.Tensor]) -> None:
        """Scores of ended plays: a stored fall takes its new score and is free again; a fresh fall joins the
        buffer while it has room, then only in place of a free stored fall that scores lower."""
        scored = ended["count"] > 0
        score = ended["sum"] / ended["count"].clamp(min=1)
        stored = ended["slot"] >= 0
        self.busy[ended["slot"][stored]] = False
        self.score[ended["slot"][stored & scored]] = score[stored & scored]
        fresh = (~stored & scored).nonzero().view(-1)
        fresh = fresh[score[fresh].argsort(descending=True)]  # the best first
        room = min(fresh.numel(), self.config.size - self.filled)
        self._store(torch.arange(self.filled, self.filled + room), fresh[:room], ended, score)
        self.filled += room
        rest = fresh[room:]
        free = (~self.busy[: self.filled]).nonzero().view(-1)
        free = free[self.score[free].argsort()][: rest.numel()]  # the lowest first
        rest = rest[: free.numel()]
        better = score[rest] > self.score[free]  # both sorted: a leading run
        self._store(free[better], rest[better], ended, score)

    def _store(self, slots: torch.Tensor, rows: torch.Tensor, ended: dict[str, torch.Tensor], score: torch.Tensor) -> None:
        self.qpos[slots], self.qvel[slots], self.pose[slots] = ended["qpos"][rows], ended["qvel"][rows], ended["pose"][rows]
        self.score[slots], self.last_played[slots] = score[rows], self.started

    def _draw(self, k: int, generator: torch.Generator) -> torch.Tensor:
        """k distinct free stored falls, by rank of score mixed with staleness (PLR's sampling)."""
        free = (~self.busy).nonzero().view(-1)
        k = min(k, free.numel())
        if k == 0:
            return free[:0]
        rank = torch.empty(free.numel(), dtype=_F64)
        rank[self.score[free].argsort(descending=True)] = torch.arange(1, free.numel() + 1, dtype=_F64)
        by_score = rank.pow(-1.0 / self.config.temperature)
        stale = (self.started - self.last_played[free]).to(_F64)
        c = self.config.staleness
        p = (1 - c) * by_score / by_score.sum() + (c * stale / stale.sum() if stale.sum() > 0 else c / free.numel())
        return free[torch.multinomial(p, k, replacement=False, generator=generator)]
