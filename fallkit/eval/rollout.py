"""Paired falls (paper Sec. V-C): every strategy from the same initial states toward the same end poses.

One FallEnv runs all strategies at once: its worlds are split into one block per
strategy, each block holding the same trials, so policy and strategies share
one code path (`env.reset_to`, `env.step`). The strategies are gain scales of
the PD controllers (`fallkit.eval.strategies`) holding the setpoint the fall
began with; the policy block keeps the nominal gains and acts. The reference
"seek" (not one of the paper's strategies) keeps the nominal gains and moves its
setpoints open-loop from the joints at the fall's start to the target joints by
u(t): what the end pose alone buys, without learning. Trials beyond one env's
worlds run in chunks (`evaluate`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Sequence

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tqdm import tqdm

from fallkit.env.fall_env import FallEnv
from fallkit.eval.metrics import FallTrace, TrialMetrics, trial_metrics
from fallkit.eval.strategies import STRATEGIES
from fallkit.sim.base import SimState

POLICY = "policy"
SEEK = "seek"  # the open-loop reference: setpoints blended to the target joints by u(t)


# ---- trials ------------------------------------------------------------------------------


@dataclass
class Trials:
    """Initial states and end-pose ids of n paired trials."""

    qpos: torch.Tensor  # [n, nq] float64
    qvel: torch.Tensor  # [n, nv] float64
    pose_ids: torch.Tensor  # [n] long, rows of the env's EndPoseSet

    def __len__(self) -> int:
        return self.qpos.shape[0]

    def take(self, index: torch.Tensor) -> "Trials":
        return Trials(self.qpos[index], self.qvel[index], self.pose_ids[index])


def draw_trials(env: FallEnv, n: int, seed: int) -> Trials:
    """n initial states drawn as in training (the env's own sampler) and end poses.

    The end poses are a shuffled cycle through the env's pose set, so every pose
    is used about equally often.
    """
    g = torch.Generator().manual_seed(seed)
    qpos, qvel = env.initial_states.sample(n, g)
    p = len(env.end_poses)
    ids = torch.cat([torch.randperm(p, generator=g) for _ in range(math.ceil(n / p))])[:n]
    return Trials(qpos, qvel, ids)


def _fit(trials: int, strategies: int, num_envs: int) -> tuple[int, int]:
    """(most trials one chunk holds, chunks for all): a trial takes one world per strategy."""
    per = max(1, num_envs // strategies)
    return per, math.ceil(trials / per)


def chunking(trials: int, strategies: int, num_envs: int) -> tuple[int, int]:
    """(trials per chunk, chunks): strategies × trials-per-chunk worlds fit in num_envs, padding kept small."""
    _, chunks = _fit(trials, strategies, num_envs)
    return math.ceil(trials / chunks), chunks


# ---- one chunk ---------------------------------------------------------------------------


@dataclass
class Rollout:
    """What one chunk of paired falls recorded; the state history only when asked for (rendering)."""

    strategies: list[str]
    traces: dict[str, FallTrace]
    qpos: torch.Tensor | None = None  # [T+1, W, nq] (index 0: the initial state)
    qvel: torch.Tensor | None = None  # [T+1, W, nv]
    joint_torque: torch.Tensor | None = None  # [T+1, W, J] actuator torque at the last substep
    setpoint: torch.Tensor | None = None  # [T+1, W, J] joint setpoints the step drove toward


def gain_scales(strategies: Sequence[str]) -> list[float]:
    """PD gain scale of each strategy (the policy keeps the nominal gains)."""
    return [STRATEGIES.get(s, 1.0) for s in strategies]


@torch.no_grad()
def rollout(
    env: FallEnv, trials: Trials, strategies: Sequence[str], policy: TensorDictModuleBase | None = None,
    steps: int | None = None, record_states: bool = False, progress: tqdm | None = None,
    on_step: Callable[[int, SimState], None] | None = None,
) -> Rollout:  # fmt: skip
    """Fall every trial once per strategy, all in the env's worlds at once.

    World block i (rows i·k … (i+1)·k−1, k = len(trials)) runs strategy i; the env
    must have exactly len(strategies)·k worlds. `policy` is a TensorDictModule
    ("policy" -> "action") and is required when "policy" is among the strategies.
    `on_step(t, state)` sees the state after every step (mode=play draws and paces the
    fall with it, so what it shows is this very rollout); an exception it raises ends the rollout.
    """
    strategies, k = list(strategies), len(trials)
    _check_blocks(env, strategies, k, policy)
    steps = env.max_steps if steps is None else steps
    td = _start(env, trials, strategies)
    # "holding the most recent setpoint": the joint angles when the fall begins
    hold = env.action_for_setpoint(env.sim.state.joint_pos.clone())
    rows = _block(strategies.index(POLICY), k) if POLICY in strategies else None
    seek = _block(strategies.index(SEEK), k) if SEEK in strategies else None
    if rows is not None:
        policy.to(env.device)  # checkpoints load on the CPU; the env may live on a GPU (sim=warp)
    rec = _Recorder(env, steps, record_states)
    rec.remember(env.sim.state, env.sim.state.joint_pos)
    start_q = env.sim.state.joint_pos.clone()
    for t in range(steps):
        action = hold.clone()
        if rows is not None:
            action[rows] = policy(td[rows].select("policy"))["action"]
        if seek is not None:
            action[seek] = seek_action(env, start_q, seek)
        td = env.step(td.set("action", action))["next"]
        rec.record(t, env.sim.state, env.setpoint(action))
        if progress is not None:
            progress.update(1)
        if on_step is not None:
            on_step(t, env.sim.state)
    return rec.result(env, trials, strategies)


def seek_action(env: FallEnv, start_q: torch.Tensor, rows: slice = slice(None)) -> torch.Tensor:
    """The seek reference's action in worlds `rows` now: the joints at the fall's start (`start_q`, all worlds)
    blended into the target joints by the tracking blend u(t), at nominal gains; no learning."""
    u = env.tracking_blend()[rows, None]
    return env.action_for_setpoint(torch.lerp(start_q[rows], env.goal_joint_pos[rows], u))


def _check_blocks(env: FallEnv, strategies: list[str], k: int, policy: TensorDictModuleBase | None) -> None:
    s, w = len(strategies), env.num_envs
    if w != s * k:
        raise ValueError(f"rollout: {s} strategies × {k} trials need {s * k} worlds, the env has {w}")
    if POLICY in strategies and policy is None:
        raise ValueError("rollout: the 'policy' strategy needs a policy")


def _block(i: int, k: int) -> slice:
    """The worlds of strategy i when every strategy runs k trials."""
    return slice(i * k, (i + 1) * k)


def _start(env: FallEnv, trials: Trials, strategies: list[str]) -> TensorDictBase:
    """Every block reset to the same trials, each with its strategy's gains."""
    s, k = len(strategies), len(trials)
    td = env.reset_to(trials.qpos.repeat(s, 1), trials.qvel.repeat(s, 1), trials.pose_ids.repeat(s))
    env.sim.set_gain_scale(torch.tensor(gain_scales(strategies), device=env.device).repeat_interleave(k))
    return td


class _Recorder:
    """Per step: contact forces (peak and mean over the substeps), root speeds, instability;
    with record_states also the state history."""

    def __init__(self, env: FallEnv, steps: int, record_states: bool):
        w, c, dev = env.num_envs, len(env.spec.components), env.device
        self.peak = torch.zeros(w, steps, c, device=dev)
        self.mean = torch.zeros(w, steps, c, device=dev)
        self.lin = torch.zeros(w, steps, device=dev)
        self.ang = torch.zeros(w, steps, device=dev)
        self.unstable = torch.zeros(w, dtype=torch.bool, device=dev)
        self.record_states = record_states
        self.history: dict[str, list[torch.Tensor]] = {"qpos": [], "qvel": [], "joint_torque": [], "setpoint": []}

    def record(self, t: int, st: SimState, setpoint: torch.Tensor) -> None:
        self.peak[:, t] = st.peak_contact_force()
        self.mean[:, t] = st.contact_force_norm().mean(dim=1)
        self.lin[:, t] = st.root_lin_vel.norm(dim=-1)
        self.ang[:, t] = st.root_ang_vel.norm(dim=-1)
        self.unstable |= st.unstable.to(self.unstable.device)
        self.remember(st, setpoint)

    def remember(self, st: SimState, setpoint: torch.Tensor) -> None:
        if self.record_states:
            for name, value in (("qpos", st.qpos), ("qvel", st.qvel), ("joint_torque", st.joint_torque)):
                self.history[name].append(value.detach().cpu().clone())
            self.history["setpoint"].append(setpoint.detach().cpu().clone())

    def result(self, env: FallEnv, trials: Trials, strategies: list[str]) -> Rollout:
        """One FallTrace per strategy block (final state: the env's now)."""
        st, k = env.sim.state, len(trials)
        poses = trials.pose_ids.to(env.device)
        target_quat = env.end_poses.root_quat[poses]
        target_q = env.end_poses.joint_pos[poses]
        traces = {}
        for i, name in enumerate(strategies):
            r = _block(i, k)
            traces[name] = FallTrace(
                peak_force=self.peak[r],
                mean_force=self.mean[r],
                root_lin_speed=self.lin[r],
                root_ang_speed=self.ang[r],
                final_root_quat=st.root_quat[r],
                final_joint_pos=st.joint_pos[r],
                target_root_quat=target_quat,
                target_joint_pos=target_q,
                unstable=self.unstable[r],
            )
        out = Rollout(strategies, traces)
        if self.record_states:
            out.qpos, out.qvel, out.joint_torque, out.setpoint = (torch.stack(v) for v in self.history.values())
        return out


# ---- many chunks ------------------------------------------------------------------------


def evaluate(
    env: FallEnv, trials: Trials, strategies: Sequence[str], policy: TensorDictModuleBase | None = None,
    steps: int | None = None, show_progress: bool = True,
) -> dict[str, TrialMetrics]:  # fmt: skip
    """Per-trial metrics of every strategy over all trials, in chunks of the env's worlds."""
    strategies = list(strategies)
    n = len(trials)
    k, chunks = _fit(n, len(strategies), env.num_envs)  # the env's worlds hold k trials
    steps = env.max_steps if steps is None else steps
    parts: dict[str, list[TrialMetrics]] = {s: [] for s in strategies}
    bar = tqdm(
        total=chunks * steps,
        desc=f"eval: {n} falls × {len(strategies)} strategies",
        unit="step",
        disable=not show_progress,
        dynamic_ncols=True,
    )
    with bar:
        for c in range(chunks):
            index = torch.arange(c * k, (c + 1) * k).clamp(max=n - 1)  # the last chunk repeats its last trial
            real = min(k, n - c * k)
            out = rollout(env, trials.take(index), strategies, policy, steps, progress=bar)
            for name, trace in out.traces.items():
                parts[name].append(trial_metrics(trace, env.dt).take(slice(0, real)))
    return {s: TrialMetrics.cat(p) for s, p in parts.items()}
