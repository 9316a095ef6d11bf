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
5. rebalancing: settled poses are binned by the direction of gravity in the root
   frame (an equal-area grid on the unit sphere) and sampling goes on until the
   over-full bins can be thinned to uniform coverage within `tolerance`; bins the
   robot reaches less often than `min_share` x a uniform share ("rare") keep all
   their poses (filling them would take many times the drops). A drop lying slowly
   in a bin that is already full is stopped early: it could only be discarded.

The drops run in a pool of `num_worlds` simulated worlds: a world that comes to
rest is recorded and immediately re-used for the next candidate, so no world
waits for the slowest drop of a batch. Everything is driven by one seeded
generator and processed in world order, so a seed gives the same dataset.
"""

from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from fallkit.config import DatasetConfig, SettleConfig
from fallkit.robots.spec import RobotSpec
from fallkit.rotations import gravity_in_frame, quat_from_euler, quat_mul
from fallkit.poses.checker import PoseChecker
from fallkit.sim import Layout, make_sim, sim_options

log = logging.getLogger(__name__)






# ---- orientation bins -------------------------------------------------------------------------


class OrientationBins:
    """Equal-area bins of the unit sphere for the ground direction in the root frame.

    The ground direction d = -R(q)ᵀ e_z names the side of the robot that faces
    the ground (+x front, -x back, +y left, -y right, -z feet, +z head). Bands
    are equal steps of d_z (Archimedes: equal areas), sectors equal steps of the
    azimuth with sector 0 centred on +x (lying on the front), so front, back and
    both sides each sit in the middle of a sector. With an even number of bands,
    lying flat (d_z = 0) is on a band boundary: slight tilts towards head or feet
    land in the two neighbouring bands.
    """

    def __init__(self, bands: int, sectors: int):
        self.bands, self.sectors = bands, sectors

    @property
    def count(self) -> int:
        return self.bands * self.sectors

    def down(self, root_quat: torch.Tensor) -> torch.Tensor:
        return -gravity_in_frame(root_quat.double())

    def index(self, root_quat: torch.Tensor) -> torch.Tensor:
        """Bin [n] (long) of each orientation [n, 4]."""
        d = self.down(root_quat)
        band = ((d[:, 2] + 1.0) * 0.5 * self.bands).long().clamp(0, self.bands - 1)
        azimuth = torch.atan2(d[:, 1], d[:, 0]) + math.pi / self.sectors  # sector 0 centred on +x
        sector = (torch.remainder(azimuth, 2 * math.pi) / (2 * math.pi) * self.sectors).long()
        return band * self.sectors + sector.clamp(0, self.sectors - 1)

    def sector_labels(self) -> list[str]:
        """The side facing the ground in each sector (degrees where there are not 8 sectors)."""
        if self.sectors == 8:
            return ["front", "front-left", "left", "back-left", "back", "back-right", "right", "front-right"]
        return [f"{360 * s / self.sectors:.0f}°" for s in range(self.sectors)]

    def describe(self) -> dict[str, Any]:
        return {
            "bands": self.bands,
            "sectors": self.sectors,
            "vector": "ground direction in the root frame, -R(q)^T e_z",
            "band": "equal steps of its z component from -1 (feet down) to +1 (head down)",
            "sector": "equal steps of atan2(y, x), sector 0 centred on +x (front down), counter-clockwise",
        }


def select_uniform(
    counts: np.ndarray, seen: np.ndarray, total: int, min_share: float
) -> tuple[np.ndarray, np.ndarray, bool]:
    """How many poses to keep per bin: (keep [K], rare [K] bool, feasible).

    counts: settled poses per bin; seen: drops per bin, including the ones
    stopped early in an over-full bin (the natural frequencies). Rare bins (seen
    less often than `min_share` of a uniform share) keep all their poses; the
    covered bins are filled to one common level ("water filling") so that
    `total` poses are kept. Infeasible when fewer than `total` poses settled.
    """
    k = len(counts)
    rare = seen < min_share * seen.sum() / k
    keep = np.where(rare, counts, 0)
    need = total - int(keep.sum())
    cov = np.flatnonzero(~rare)
    if need <= 0 or len(cov) == 0:
        # hardly possible (rare bins alone hold `total`); take the rare ones in bin order
        keep = np.minimum(counts, np.maximum(0, total - (np.cumsum(counts) - counts)))
        return keep, rare, need <= 0
    if counts[cov].sum() < need:
        keep[cov] = counts[cov]
        return keep, rare, False
    # the largest level L with sum(min(counts, L)) <= need, then the remainder one by one
    c = np.sort(counts[cov])
    level, before = 0, 0
    for i, ci in enumerate(c):
        filled = before + ci * (len(c) - i)
        if filled >= need:
            level = (need - before) // (len(c) - i)
            break
        before += ci
    else:  # pragma: no cover - excluded by the sum check above
        level = int(c[-1])
    keep[cov] = np.minimum(counts[cov], level)
    rest = need - int(keep[cov].sum())
    for b in cov:  # bins still above the level take one more each, in bin order
        if rest == 0:
            break
        if counts[b] > level:
            keep[b] += 1
            rest -= 1
    return keep, rare, True


def uniformity(keep: np.ndarray, rare: np.ndarray) -> float:
    """Smallest / largest kept count over the covered bins (1 = perfectly uniform)."""
    cov = keep[~rare]
    return float(cov.min() / cov.max()) if len(cov) and cov.max() > 0 else 0.0


# ---- drops -------------------------------------------------------------------------------


def sample_root_quat(n: int, generator: torch.Generator) -> torch.Tensor:
    """Pitch then yaw about the robot's own pitched z axis, each uniform in ±180° (paper Sec. IV-C)."""
    pitch = (2.0 * torch.rand(n, generator=generator, dtype=torch.float64) - 1.0) * math.pi
    yaw = (2.0 * torch.rand(n, generator=generator, dtype=torch.float64) - 1.0) * math.pi
    zero = torch.zeros_like(pitch)
    # intrinsic order: q = q_pitch ⊗ q_yaw (the yaw turns the already pitched body about its own z)
    return quat_mul(quat_from_euler(zero, pitch, zero), quat_from_euler(zero, zero, yaw))


class RestDetector:
    """Per-world at-rest bookkeeping in policy steps (thresholds of SettleConfig)."""

    def __init__(self, n: int, cfg: SettleConfig, policy_dt: float):
        self.cfg = cfg
        self.rest_steps = max(1, math.ceil(cfg.rest_time / policy_dt - 1e-9))
        self.max_steps = max(1, math.ceil(cfg.max_time / policy_dt - 1e-9))
        self.age = torch.zeros(n, dtype=torch.long)
        self.calm = torch.zeros(n, dtype=torch.long)

    def restart(self, ids: torch.Tensor) -> None:
        self.age[ids] = 0
        self.calm[ids] = 0

    def update(self, state: "_Cpu") -> tuple[torch.Tensor, torch.Tensor]:
        """After a step: (at rest [n], timed out [n])."""
        c = self.cfg
        quiet = (state.lin_speed < c.lin_vel) & (state.ang_speed < c.ang_vel) & (state.joint_speed < c.joint_vel)
        self.age += 1
        self.calm = torch.where(quiet, self.calm + 1, torch.zeros_like(self.calm))
        at_rest = self.calm >= self.rest_steps
        return at_rest, (self.age >= self.max_steps) & ~at_rest


@dataclass
class _Cpu:
    """What the drop bookkeeping reads of a SimState, on the CPU (the sim may live on a GPU)."""

    qpos: torch.Tensor
    root_quat: torch.Tensor
    root_height: torch.Tensor
    joint_pos: torch.Tensor
    lin_speed: torch.Tensor
    ang_speed: torch.Tensor
    joint_speed: torch.Tensor
    unstable: torch.Tensor

    @classmethod
    def of(cls, st) -> "_Cpu":
        return cls(
            qpos=st.qpos.cpu(),
            root_quat=st.root_quat.cpu(),
            root_height=st.root_pos[:, 2].cpu(),
            joint_pos=st.joint_pos.cpu(),
            lin_speed=st.root_lin_vel.norm(dim=1).cpu(),
            ang_speed=st.root_ang_vel.norm(dim=1).cpu(),
            joint_speed=st.joint_vel.abs().amax(dim=1).cpu(),
            unstable=st.unstable.cpu(),
        )


@dataclass
class SettleResult:
    qpos: torch.Tensor  # [n, nq] float64, the state at rest (or at the time cap)
    settled: torch.Tensor  # [n] bool
    seconds: torch.Tensor  # [n] simulated time until rest


def settle(
    spec: RobotSpec,
    qpos: torch.Tensor,
    cfg: SettleConfig | None = None,
    setpoint: torch.Tensor | None = None,
    backend: str = "mujoco",
    **sim_options: Any,
) -> SettleResult:
    """Simulate poses [n, nq] with frozen gains until each is at rest (or the time cap).

    The joints hold `setpoint` [n, J] (default: the joint angles of qpos). Used
    for the artist poses and to check that a settled pose stays put; the
    generator runs the same procedure in a refilling pool.
    """
    cfg = cfg or SettleConfig()
    n = qpos.shape[0]
    sim = make_sim(spec, n, backend, **sim_options)
    lay = Layout(spec)
    qpos = qpos.to(torch.float64)
    hold = (qpos[:, lay.joint_qpos] if setpoint is None else setpoint).to(torch.float32)
    sim.reset(torch.arange(n), qpos, torch.zeros(n, lay.nv, dtype=torch.float64))
    sim.set_gain_scale(torch.full((n,), cfg.gain_scale))
    rest = RestDetector(n, cfg, spec.policy_dt)
    done = torch.zeros(n, dtype=torch.bool)
    settled = torch.zeros(n, dtype=torch.bool)
    final = qpos.clone()
    seconds = torch.full((n,), float("nan"))
    hold = hold.to(sim.device)
    while not done.all():
        st = _Cpu.of(sim.step(hold))
        at_rest, timeout = rest.update(st)
        new = ~done & (at_rest | timeout | st.unstable)
        ok = new & at_rest & ~st.unstable
        final[new] = st.qpos[new].double()
        settled |= ok
        seconds[ok] = rest.age[ok].float() * spec.policy_dt
        done |= new
    return SettleResult(final, settled, seconds)


# ---- the generator --------------------------------------------------------------------------


@dataclass
class GeneratedPoses:
    """Result of a generation run: the kept poses in drop order, and what happened."""

    joint_pos: torch.Tensor  # [P, J] settled joint angles, policy order
    root_quat: torch.Tensor  # [P, 4] settled root orientation (w, x, y, z)
    root_height: torch.Tensor  # [P] settled root height [m]
    bin: torch.Tensor  # [P] orientation bin
    split: np.ndarray  # [P] "train" | "test"
    stats: dict[str, Any] = field(default_factory=dict)


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
            lay = self.checker.layout
            qpos = lay.qpos(torch.zeros(self.block, 3, dtype=torch.float64), quat, joints)
            qpos, _ = self.checker.place_on_ground(qpos, self.drop_height)
            self._qpos = torch.cat((self._qpos, qpos))
            self._joints = torch.cat((self._joints, joints))
        q, j = self._qpos[:n], self._joints[:n]
        self._qpos, self._joints = self._qpos[n:], self._joints[n:]
        return q, j


class EndPoseGenerator:
    """Generates an end-pose dataset for one robot (see module docstring)."""

    def __init__(self, spec: RobotSpec, config: DatasetConfig | None = None, backend: str = "mujoco", **sim_options: Any):
        self.spec = spec
        self.config = config or DatasetConfig()
        self.backend = backend
        self.sim_options = sim_options
        self.bins = OrientationBins(self.config.bands, self.config.sectors)

    def run(self, progress: bool = True) -> GeneratedPoses:
        cfg, spec = self.config, self.spec
        total = cfg.train + cfg.test
        W = cfg.num_worlds
        K = self.bins.count
        g = torch.Generator().manual_seed(cfg.seed)
        checker = PoseChecker(spec)
        lay = checker.layout
        cands = _Candidates(checker, g, cfg.settle.drop_height, block=max(256, min(4096, W)))
        sim = make_sim(spec, W, self.backend, **self.sim_options)
        sim.set_gain_scale(torch.full((W,), cfg.settle.gain_scale))
        rest = RestDetector(W, cfg.settle, spec.policy_dt)
        zero_v = torch.zeros(W, lay.nv, dtype=torch.float64)
        qpos, joints = cands.take(W)
        sim.reset(torch.arange(W), qpos, zero_v)
        hold = joints.float().to(sim.device)
        last_bin = torch.full((W,), -1, dtype=torch.long)
        in_full = torch.zeros(W, dtype=torch.long)  # steps spent slowly in one over-full bin

        counts = np.zeros(K, np.int64)  # settled poses per bin
        seen = np.zeros(K, np.int64)  # settled or stopped early, per bin: the natural frequencies
        kept_q, kept_j, kept_h, kept_b = [], [], [], []  # every settled pose, in drop order
        n = {"drops": W, "unsettled": 0, "unstable": 0, "aborted_overfull": 0}
        steps = settle_steps = 0
        max_drops = int(cfg.max_drops * total)
        keep, rare, feasible, done = counts, np.zeros(K, bool), False, False
        t0 = time.perf_counter()
        bar = tqdm(total=total, desc=f"end poses ({spec.name})", unit="pose", disable=not progress, mininterval=1.0)
        while True:
            st = _Cpu.of(sim.step(hold))
            steps += 1
            at_rest, timeout = rest.update(st)
            bad = st.unstable
            ok = at_rest & ~bad
            if ok.any():
                idx = torch.nonzero(ok).squeeze(1)  # world order: deterministic
                b = self.bins.index(st.root_quat[idx])
                kept_q.append(st.root_quat[idx].clone())
                kept_j.append(st.joint_pos[idx].clone())
                kept_h.append(st.root_height[idx].clone())
                kept_b.append(b)
                landed = np.bincount(b.numpy(), minlength=K)
                counts += landed
                seen += landed
                settle_steps += int(rest.age[idx].sum())
            n["unsettled"] += int((timeout & ~bad).sum())
            n["unstable"] += int(bad.sum())
            keep, rare, feasible = select_uniform(counts, seen, total, cfg.min_share)
            done = feasible and uniformity(keep, rare) >= 1.0 - cfg.tolerance
            # Early abort: a drop lying slowly in a bin that is already full can only be
            # discarded (full: it holds the most any covered bin can keep), so stop it.
            level = (total - counts[rare].sum()) / max(1, int((~rare).sum()))
            full = torch.from_numpy(~rare & (counts >= level))
            now_bin = self.bins.index(st.root_quat)
            slow = (st.lin_speed < cfg.abort_lin_vel) & (st.ang_speed < cfg.abort_ang_vel)
            in_full = torch.where(slow & full[now_bin] & (now_bin == last_bin), in_full + 1, torch.zeros_like(in_full))
            last_bin = now_bin
            abort = ~(ok | timeout | bad) & (in_full >= cfg.abort_steps) if cfg.abort_steps > 0 else torch.zeros_like(ok)
            n["aborted_overfull"] += int(abort.sum())
            seen += np.bincount(now_bin[abort].numpy(), minlength=K)
            finished = ok | timeout | bad | abort
            useful = int(np.where(rare, counts, np.minimum(counts, math.ceil(level))).sum())
            bar.update(max(0, min(total, useful) - bar.n))
            bar.set_postfix(drops=n["drops"], uniform=f"{uniformity(keep, rare):.2f}", refresh=False)
            if done or n["drops"] >= max_drops:
                break
            ids = torch.nonzero(finished).squeeze(1)
            if len(ids):
                qpos, joints = cands.take(len(ids))
                sim.reset(ids, qpos, zero_v[: len(ids)])
                hold[ids.to(sim.device)] = joints.float().to(sim.device)
                rest.restart(ids)
                in_full[ids] = 0
                last_bin[ids] = -1
                n["drops"] += len(ids)
        if done:
            bar.update(total - bar.n)
        bar.close()
        seconds = time.perf_counter() - t0
        if not feasible:
            raise RuntimeError(
                f"end poses ({spec.name}): only {int(counts.sum())} of {total} poses came to rest in {n['drops']} drops "
                f"({n['unsettled']} not at rest within {cfg.settle.max_time:g} s, {n['unstable']} unstable); "
                f"raise dataset.max_drops or dataset.settle.max_time"
            )
        achieved = uniformity(keep, rare)
        if not done:
            log.warning(
                "end poses: stopped at dataset.max_drops=%g x %d drops with the covered bins uniform to %.2f only "
                "(tolerance %.2f asks for %.2f); raise max_drops or min_share, or use fewer bins",
                cfg.max_drops, total, achieved, cfg.tolerance, 1.0 - cfg.tolerance,
            )

        root_quat = torch.cat(kept_q).double()
        # MuJoCo's joint limits are soft: a loaded joint may rest up to ~0.02 rad past its limit.
        lim = torch.as_tensor(spec.joint_limits)
        joint_pos = torch.cat(kept_j).double().clamp(lim[:, 0], lim[:, 1])
        height = torch.cat(kept_h).double()
        bins = torch.cat(kept_b)
        pick = _take_per_bin(bins.numpy(), keep)  # the first poses of each bin, in drop order
        split = _stratified_split(bins.numpy()[pick], cfg.test, g)
        order = torch.randperm(len(pick), generator=g).numpy()  # random order: any prefix is a random subset
        order = np.concatenate([order[split[order] == "train"], order[split[order] == "test"]])
        pick, split = pick[order], split[order]
        stats = {
            **n,
            "settled": int(counts.sum()),
            "in_flight_at_stop": int((~finished).sum()),
            "discarded_overfull": int(counts.sum() - keep.sum()),
            "kept": int(keep.sum()),
            "hist_before": seen.tolist(),
            "hist_settled": counts.tolist(),
            "hist_after": keep.tolist(),
            "rare_bins": np.flatnonzero(rare).tolist(),
            "uniformity": achieved,
            "uniform_within_tolerance": bool(done),
            "mean_settle_seconds": settle_steps * spec.policy_dt / max(1, int(counts.sum())),
            "policy_steps": steps,
            "physics_steps": steps * sim.substeps * W,
            "seconds": seconds,
        }
        return GeneratedPoses(
            joint_pos=joint_pos[pick],
            root_quat=root_quat[pick],
            root_height=height[pick],
            bin=bins[pick],
            split=split,
            stats=stats,
        )


def _take_per_bin(bins: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """Indices of the first keep[b] poses of every bin b (drop order), ascending."""
    order = np.argsort(bins, kind="stable")
    start = np.searchsorted(bins[order], np.arange(len(keep)))
    rank = np.empty(len(bins), np.int64)
    rank[order] = np.arange(len(bins)) - start[bins[order]]
    return np.flatnonzero(rank < keep[bins])


def _stratified_split(bins: np.ndarray, test: int, g: torch.Generator) -> np.ndarray:
    """'train'/'test' per pose, with every bin's share of the test set proportional to its size."""
    n = len(bins)
    split = np.full(n, "train", dtype="<U5")
    if test == 0:
        return split
    sizes = np.bincount(bins, minlength=int(bins.max()) + 1)
    exact = sizes * test / n
    quota = np.floor(exact).astype(np.int64)
    extra = test - int(quota.sum())
    quota[np.argsort(-(exact - quota), kind="stable")[:extra]] += 1  # largest remainders
    shuffled = torch.randperm(n, generator=g).numpy()
    taken = np.zeros_like(sizes)
    for i in shuffled:
        b = bins[i]
        if taken[b] < quota[b]:
            split[i] = "test"
            taken[b] += 1
    return split


# ---- the dataset ------------------------------------------------------------------------------


def to_dataset(spec: RobotSpec, gen: GeneratedPoses, config: DatasetConfig, backend: str):
    """The generated poses as a PoseDataset with its provenance."""
    from fallkit import __version__
    from fallkit.poses.files import PoseDataset

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


def format_histogram(counts: list[int] | np.ndarray, bins: OrientationBins, rare: list[int] = ()) -> str:
    """The bins as a text table (bands as rows, head-down band first), rare bins marked *."""
    grid = np.asarray(counts).reshape(bins.bands, bins.sectors)
    edges = np.linspace(-1, 1, bins.bands + 1)
    head = " " * 13 + "".join(f"{s:>12s}" for s in bins.sector_labels())
    rows = [head]
    for b in reversed(range(bins.bands)):
        cells = "".join(f"{grid[b, s]:>11d}{'*' if b * bins.sectors + s in rare else ' '}" for s in range(bins.sectors))
        rows.append(f"z {edges[b]:+.2f}..{edges[b + 1]:+.2f}" + cells)
    return "\n".join(rows)




