"""Physics-informed end-pose generation (paper Sec. IV-C).

1. joint configurations uniform within the limits, self-colliding ones discarded
   (`PoseChecker.sample_joints`, MuJoCo's own collision detection);
2. the root orientation: a pitch rotation, then a yaw rotation about the robot's
   own (pitched) vertical axis, each uniform over ±180°, so every side of the
   robot can face the ground;
3. a drop from 0.04 m above the ground with the actuators frozen (gains × 10,
   the "freeze" strategy, holding the sampled setpoint) until the robot is at
   rest: root and joint speeds below thresholds for `rest_time`, or discarded
   (and counted) at `max_time`;
4. the settled joint angles and root orientation are the end pose;
5. rebalancing: settled poses are classed by the side facing the ground and binned
   by the direction of gravity in the root frame (an equal-area grid on the unit
   sphere), and sampling goes on until the over-full sides, and the over-full bins
   within each side, can be thinned to uniform coverage within `tolerance`
   (`fallkit.poses.balance`); sides reached less often than `side_min_share` x a
   uniform share, and side parts of bins reached less often than `min_share` x
   theirs ("rare") are left out of that test (filling them would take many times
   the drops). A drop lying slowly in a cell that is already full is stopped early:
   it could only be discarded.

The drops run in a pool of `num_worlds` simulated worlds: a world that comes to
rest is recorded and immediately re-used for the next candidate, so no world
waits for the slowest drop of a batch. Everything is driven by one seeded
generator and processed in world order, so a seed gives the same dataset.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np
import torch
from tqdm import tqdm

from fallkit import __version__
from fallkit.config import DatasetConfig
from fallkit.errors import ConfigError
from fallkit.poses.balance import Balance
from fallkit.poses.bins import SIDES, OrientationBins, pick_and_split
from fallkit.poses.checker import PoseChecker
from fallkit.poses.dataset import PoseDataset
from fallkit.poses.settle import CpuState, RestDetector
from fallkit.robots.spec import RobotSpec
from fallkit.rotations import quat_from_euler, quat_mul
from fallkit.sim import make_sim

log = logging.getLogger(__name__)


@dataclass
class GeneratedPoses:
    """Result of a generation run: the kept poses in drop order, and what happened."""

    joint_pos: torch.Tensor  # [P, J] settled joint angles, policy order
    root_quat: torch.Tensor  # [P, 4] settled root orientation (w, x, y, z)
    root_height: torch.Tensor  # [P] settled root height [m]
    bin: torch.Tensor  # [P] orientation bin
    split: np.ndarray  # [P] "train" | "test"
    stats: dict[str, Any] = field(default_factory=dict)


# ---- drop candidates ----------------------------------------------------------------------------


def sample_root_quat(n: int, generator: torch.Generator) -> torch.Tensor:
    """Pitch then yaw about the robot's own pitched z axis, each uniform in ±180° (paper Sec. IV-C)."""
    pitch = (2.0 * torch.rand(n, generator=generator, dtype=torch.float64) - 1.0) * math.pi
    yaw = (2.0 * torch.rand(n, generator=generator, dtype=torch.float64) - 1.0) * math.pi
    zero = torch.zeros_like(pitch)
    # intrinsic order: q = q_pitch ⊗ q_yaw (the yaw turns the already pitched body about its own z)
    return quat_mul(quat_from_euler(zero, pitch, zero), quat_from_euler(zero, zero, yaw))


class _Candidates:
    """Drop candidates in blocks: collision-free joints, random orientation, 0.04 m above the floor."""

    def __init__(self, checker: PoseChecker, generator: torch.Generator, drop_height: float, block: int):
        self.checker, self.g, self.drop_height, self.block = checker, generator, drop_height, block
        self._qpos = torch.empty(0, checker.layout.nq, dtype=torch.float64)
        self._joints = torch.empty(0, len(checker.spec.joints), dtype=torch.float64)

    def take(self, n: int) -> tuple[torch.Tensor, torch.Tensor]:
        while len(self._qpos) < n:
            joints = self.checker.sample_joints(self.block, self.g)
            quat = sample_root_quat(self.block, self.g)
            qpos, _ = self.checker.on_ground(quat, joints, self.drop_height)
            self._qpos = torch.cat((self._qpos, qpos))
            self._joints = torch.cat((self._joints, joints))
        q, j = self._qpos[:n], self._joints[:n]
        self._qpos, self._joints = self._qpos[n:], self._joints[n:]
        return q, j

    def place(self, quat: torch.Tensor, joints: torch.Tensor) -> torch.Tensor:
        """qpos of candidates turned to other root orientations, 0.04 m above the floor again."""
        return self.checker.on_ground(quat, joints, self.drop_height)[0]


# ---- the pool of drops and its bookkeeping ----------------------------------------------------


class _DropPool:
    """Up to `num_worlds` drops in flight; a finished world is refilled with the next candidate
    until `budget` drops have started, then left idle until the drops in flight have ended.

    The pool never starts more worlds than the budget: a request for 50 poses (budget 300)
    must not start 1024 drops and stop before any of them has landed.
    """

    def __init__(
        self, spec: RobotSpec, cfg: DatasetConfig, g: torch.Generator, backend: str, sim_options: dict, budget: int
    ):
        w = max(1, min(cfg.num_worlds, budget))
        self.cfg, self.budget = cfg, budget
        checker = PoseChecker(spec)
        self.cands = _Candidates(checker, g, cfg.settle.drop_height, block=max(256, min(4096, w)))
        self.sim = make_sim(spec, w, backend, **sim_options)
        self.sim.set_gain_scale(torch.full((w,), cfg.settle.gain_scale))
        self.rest = RestDetector(w, cfg.settle, spec.policy_dt)
        self.zero_v = torch.zeros(w, checker.layout.nv, dtype=torch.float64)
        qpos, joints = self.cands.take(w)
        self.sim.reset(torch.arange(w), qpos, self.zero_v)
        self.hold = joints.float().to(self.sim.device)
        self.last_cell = torch.full((w,), -1, dtype=torch.long)
        self.in_full = torch.zeros(w, dtype=torch.long)  # steps spent slowly in one over-full bin
        self.active = torch.ones(w, dtype=torch.bool)  # a drop is in flight (idle once the budget is spent)
        self.targeted = torch.zeros(w, dtype=torch.bool)  # its orientation was aimed at a bin short of poses
        self.drops = w
        self.steps = 0

    def step(self) -> tuple[CpuState, torch.Tensor, torch.Tensor]:
        """One policy step of every world: (state, at rest [W], timed out [W])."""
        st = CpuState.of(self.sim.step(self.hold))
        self.steps += 1
        at_rest, timeout = self.rest.update(st)
        return st, at_rest, timeout

    def stop_overfull(
        self, st: CpuState, ended: torch.Tensor, full: torch.Tensor, bins: OrientationBins
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Drops to stop early (lying slowly in a full cell for `abort_steps`), and every world's cell now."""
        cfg = self.cfg
        now_cell = bins.cell(st.root_quat)
        slow = (st.lin_speed < cfg.abort_lin_vel) & (st.ang_speed < cfg.abort_ang_vel)
        stays = slow & full[now_cell] & (now_cell == self.last_cell)
        self.in_full = torch.where(stays, self.in_full + 1, torch.zeros_like(self.in_full))
        self.last_cell = now_cell
        abort = ~ended & (self.in_full >= cfg.abort_steps) if cfg.abort_steps > 0 else torch.zeros_like(ended)
        abort &= self.active
        return abort, now_cell

    def refill(self, finished: torch.Tensor, aim: Callable[[int], tuple[torch.Tensor, torch.Tensor]]) -> None:
        """Start the next candidates in the finished worlds (in world order) while the budget lasts;
        `aim(n)` says which of them to turn toward a cell short of poses, and their orientations."""
        ids = torch.nonzero(finished & self.active).squeeze(1)
        room = max(0, self.budget - self.drops)
        self.active[ids[room:]] = False
        ids = ids[:room]
        if len(ids):
            qpos, joints = self.cands.take(len(ids))
            targeted, quat = aim(len(ids))
            if targeted.any():
                qpos[targeted] = self.cands.place(quat, joints[targeted])
            self.targeted[ids] = targeted
            self.sim.reset(ids, qpos, self.zero_v[: len(ids)])
            self.hold[ids.to(self.sim.device)] = joints.float().to(self.sim.device)
            self.rest.restart(ids)
            self.in_full[ids] = 0
            self.last_cell[ids] = -1
            self.drops += len(ids)


class _Tally:
    """What the drops produced: every settled pose in drop order, and the counts per cell
    (side x bin, flat: side x bins.count + bin)."""

    def __init__(self, k: int):
        self.counts = np.zeros(len(SIDES) * k, np.int64)  # settled poses per cell
        # settled or stopped early, per cell, of the untargeted drops only: the natural frequencies
        self.seen = np.zeros(len(SIDES) * k, np.int64)
        self.quat: list[torch.Tensor] = []
        self.joints: list[torch.Tensor] = []
        self.height: list[torch.Tensor] = []
        self.cells: list[torch.Tensor] = []
        self.unsettled = self.unstable = self.aborted_overfull = 0
        self.settle_steps = 0

    def record(self, st: CpuState, ok: torch.Tensor, age: torch.Tensor, bins: OrientationBins,
               targeted: torch.Tensor) -> None:  # fmt: skip
        """Keep the poses of the worlds at rest (`ok`), in world order: deterministic."""
        idx = torch.nonzero(ok).squeeze(1)
        c = bins.cell(st.root_quat[idx])
        self.quat.append(st.root_quat[idx].clone())
        self.joints.append(st.joint_pos[idx].clone())
        self.height.append(st.root_height[idx].clone())
        self.cells.append(c)
        self.counts += np.bincount(c.numpy(), minlength=len(self.counts))
        self.seen += np.bincount(c[~targeted[idx]].numpy(), minlength=len(self.counts))
        self.settle_steps += int(age[idx].sum())


# ---- the generator --------------------------------------------------------------------------------


class EndPoseGenerator:
    """Generates an end-pose dataset for one robot (see module docstring; config section `dataset:`)."""

    def __init__(self, spec: RobotSpec, config: DatasetConfig | None = None, backend: str = "mujoco", **sim_options: Any):
        self.spec = spec
        self.config = config or DatasetConfig()
        self.backend = backend
        self.sim_options = sim_options
        self.bins = OrientationBins(self.config.bands, self.config.sectors)
        self.area = self.bins.cell_areas()  # [sides, bins]

    def run(self, progress: bool = True) -> GeneratedPoses:
        cfg, spec = self.config, self.spec
        total = cfg.train + cfg.test
        g = torch.Generator().manual_seed(cfg.seed)
        max_drops = int(math.ceil(cfg.max_drops * total))
        pool = _DropPool(spec, cfg, g, self.backend, self.sim_options, budget=max_drops)
        tally = _Tally(self.bins.count)
        t0 = time.perf_counter()
        bar = tqdm(total=total, desc=f"end poses ({spec.name})", unit="pose", disable=not progress, mininterval=1.0)
        while True:
            balance, finished = self._step(pool, tally, total)
            self._show(bar, pool, tally, balance, total)
            if balance.done:
                break
            pool.refill(finished, lambda n, b=balance: self._aim(n, b, tally, g))
            if not pool.active.any():  # the budget is spent and every drop has ended
                break
        if balance.done:
            bar.update(total - bar.n)
        bar.close()
        seconds = time.perf_counter() - t0
        self._check(pool, tally, balance, total)
        stats = self._stats(pool, tally, balance, finished, seconds)
        return self._select(tally, balance.keep, g, stats)

    def _balance(self, tally: _Tally, total: int) -> Balance:
        cfg, shape = self.config, self.area.shape
        return Balance.of(
            tally.counts.reshape(shape), tally.seen.reshape(shape), self.area, total,
            min_share=cfg.min_share, side_min_share=cfg.side_min_share, tolerance=cfg.tolerance,
        )  # fmt: skip

    def _step(self, pool: _DropPool, tally: _Tally, total: int) -> tuple[Balance, torch.Tensor]:
        """Step the drops, record the settled poses, stop the hopeless ones: (rebalancing, finished [W])."""
        st, at_rest, timeout = pool.step()
        at_rest, timeout = at_rest & pool.active, timeout & pool.active  # idle worlds record nothing
        bad = st.unstable & pool.active
        ok = at_rest & ~bad
        if ok.any():
            tally.record(st, ok, pool.rest.age, self.bins, pool.targeted)
        tally.unsettled += int((timeout & ~bad).sum())
        tally.unstable += int(bad.sum())
        balance = self._balance(tally, total)
        # Early abort: a drop lying slowly in a cell that is already full can only be
        # discarded (full: it holds the most that cell can keep), so stop it.
        ended = ok | timeout | bad
        full = torch.from_numpy(balance.full(tally.counts.reshape(self.area.shape)).ravel())
        abort, now_cell = pool.stop_overfull(st, ended, full, self.bins)
        tally.aborted_overfull += int(abort.sum())
        tally.seen += np.bincount(now_cell[abort & ~pool.targeted].numpy(), minlength=len(tally.seen))
        return balance, ended | abort

    def _aim(self, n: int, balance: Balance, tally: _Tally, g: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        """Which of n new drops to aim at covered cells still short of their cap (a `targeted` share,
        cells in proportion to what they lack) and their orientations; the others keep the paper's
        uniform orientation. With targeted = 0 nothing is drawn: the same seed, the same dataset."""
        aim = torch.zeros(n, dtype=torch.bool)
        short = np.where(balance.rare, 0.0, balance.cap - tally.counts.reshape(self.area.shape)).ravel()
        short = np.nan_to_num(np.maximum(short, 0.0), posinf=0.0)
        if self.config.targeted == 0 or short.sum() <= 0:
            return aim, torch.empty(0, 4, dtype=torch.float64)
        aim = torch.rand(n, generator=g, dtype=torch.float64) < self.config.targeted
        cells = torch.multinomial(torch.from_numpy(short), max(1, int(aim.sum())), replacement=True, generator=g)
        return aim, self.bins.sample_cells(cells[: int(aim.sum())], g)

    def _show(self, bar: tqdm, pool: _DropPool, tally: _Tally, balance: Balance, total: int) -> None:
        bar.update(max(0, min(total, balance.useful(tally.counts.reshape(self.area.shape))) - bar.n))
        bar.set_postfix(drops=pool.drops, uniform=f"{balance.uniformity:.2f}", refresh=False)

    def _check(self, pool: _DropPool, tally: _Tally, balance: Balance, total: int) -> None:
        """Fail when too few poses came to rest; warn when the bins did not become uniform."""
        cfg = self.config
        if not balance.feasible:
            raise ConfigError(
                f"end poses ({self.spec.name}): only {int(tally.counts.sum())} of {total} poses came to rest in "
                f"{pool.drops} drops ({tally.unsettled} not at rest within {cfg.settle.max_time:g} s, "
                f"{tally.unstable} unstable); raise dataset.max_drops or dataset.settle.max_time"
            )
        if not balance.done:
            log.warning(
                "end poses: stopped at dataset.max_drops=%g x %d drops with the covered sides and bins uniform to "
                "%.2f only (tolerance %.2f asks for %.2f); raise max_drops, min_share or side_min_share, or use "
                "fewer bins",
                cfg.max_drops, total, balance.uniformity, cfg.tolerance, 1.0 - cfg.tolerance,
            )  # fmt: skip

    def _stats(
        self, pool: _DropPool, tally: _Tally, balance: Balance, finished: torch.Tensor, seconds: float
    ) -> dict[str, Any]:
        settled = int(tally.counts.sum())
        seen, counts = tally.seen.reshape(self.area.shape), tally.counts.reshape(self.area.shape)
        return {
            "drops": pool.drops,
            "unsettled": tally.unsettled,
            "unstable": tally.unstable,
            "aborted_overfull": tally.aborted_overfull,
            "settled": settled,
            "in_flight_at_stop": int((pool.active & ~finished).sum()),
            "discarded_overfull": int(tally.counts.sum() - balance.keep.sum()),
            "kept": int(balance.keep.sum()),
            "hist_before": seen.sum(0).tolist(),  # per bin, the sides together
            "hist_settled": counts.sum(0).tolist(),
            "hist_after": balance.keep.sum(0).tolist(),
            "rare_bins": np.flatnonzero(balance.rare.all(0)).tolist(),  # no part of the bin in the test
            "sides": list(SIDES),
            "sides_before": seen.sum(1).tolist(),
            "sides_after": balance.keep.sum(1).tolist(),
            "rare_sides": [SIDES[i] for i in np.flatnonzero(balance.rare_side)],
            "cells_before": seen.tolist(),  # [sides][bins]
            "cells_after": balance.keep.tolist(),
            "uniformity": balance.uniformity,
            "uniform_within_tolerance": bool(balance.done),
            "mean_settle_seconds": tally.settle_steps * self.spec.policy_dt / max(1, settled),
            "policy_steps": pool.steps,
            "physics_steps": pool.steps * pool.sim.substeps * self.config.num_worlds,
            "seconds": seconds,
        }

    def _select(self, tally: _Tally, keep: np.ndarray, g: torch.Generator, stats: dict[str, Any]) -> GeneratedPoses:
        """The kept poses, split into train and test."""
        root_quat = torch.cat(tally.quat).double()
        # MuJoCo's joint limits are soft: a loaded joint may rest up to ~0.02 rad past its limit.
        lim = torch.as_tensor(self.spec.joint_limits)
        joint_pos = torch.cat(tally.joints).double().clamp(lim[:, 0], lim[:, 1])
        height = torch.cat(tally.height).double()
        cells = torch.cat(tally.cells)
        bins = cells % self.bins.count
        pick, split = pick_and_split(cells.numpy(), keep.ravel(), self.config.test, g)
        return GeneratedPoses(
            joint_pos=joint_pos[pick],
            root_quat=root_quat[pick],
            root_height=height[pick],
            bin=bins[pick],
            split=split,
            stats=stats,
        )


# ---- the dataset ------------------------------------------------------------------------------


def to_dataset(spec: RobotSpec, gen: GeneratedPoses, config: DatasetConfig, backend: str) -> PoseDataset:
    """The generated poses as a PoseDataset with its provenance."""
    return PoseDataset(
        robot=spec.name,
        model_hash=spec.model_hash(),
        joint_names=list(spec.joint_names),
        joint_pos=gen.joint_pos.numpy().astype(np.float32),
        root_quat=gen.root_quat.numpy().astype(np.float32),
        root_height=gen.root_height.numpy().astype(np.float32),
        split=gen.split,
        bin=gen.bin.numpy().astype(np.int16),
        meta={
            "seed": config.seed,
            "generator": {"name": "end_poses", "backend": backend, "fallkit": __version__, **config.model_dump()},
            "bins": OrientationBins(config.bands, config.sectors).describe(),
            "stats": {k: v for k, v in gen.stats.items() if k not in ("seconds",)},  # same seed, same file content
        },
    )
