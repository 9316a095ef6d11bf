"""`mode=eval`: a policy against the standard fall strategies, with the paper's metrics.

Paired comparison (paper Sec. V-C): every strategy falls from the same initial
states toward the same end poses. One FallEnv runs all of them at once: its
worlds are split into one block per strategy, each block holding the same
trials, so policy and strategies share one code path (`env.reset_to`,
`env.step`). The strategies are gain scales of the PD controllers
(`fallkit.eval.strategies`) holding the setpoint the fall began with; the policy
block keeps the nominal gains and acts. Trials beyond one env's worlds run in
chunks. Evaluation runs without observation noise and disturbance forces, so
the comparison is deterministic and stays paired.

Outputs in the run dir: eval.json (one object per strategy), eval.md (tables),
eval_trials.npz (every per-trial figure) and the PNG plots of `fallkit.eval.plots`.
"""

from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np
import torch
from tqdm import tqdm

from fallkit.config import FallkitConfig
from fallkit.env.build import make_env
from fallkit.env.fall_env import FallEnv
from fallkit.errors import ConfigError
from fallkit.eval import plots
from fallkit.eval.metrics import FallTrace, TrialMetrics, summarize_trials, trial_metrics
from fallkit.eval.strategies import STRATEGIES
from fallkit.rl.policy import load_policy
from fallkit.robots import robot_spec

if TYPE_CHECKING:
    from tensordict.nn import TensorDictModuleBase

log = logging.getLogger(__name__)

POLICY = "policy"




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


def chunking(trials: int, strategies: int, num_envs: int) -> tuple[int, int]:
    """(trials per chunk, chunks): strategies × trials-per-chunk worlds fit in num_envs, padding kept small."""
    per = max(1, num_envs // strategies)
    chunks = math.ceil(trials / per)
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
    return [1.0 if s == POLICY else STRATEGIES[s] for s in strategies]


@torch.no_grad()
def rollout(
    env: FallEnv,
    trials: Trials,
    strategies: Sequence[str],
    policy: TensorDictModuleBase | None = None,
    steps: int | None = None,
    record_states: bool = False,
    progress: tqdm | None = None,
) -> Rollout:
    """Fall every trial once per strategy, all in the env's worlds at once.

    World block i (rows i·k … (i+1)·k−1, k = len(trials)) runs strategy i; the env
    must have exactly len(strategies)·k worlds. `policy` is a TensorDictModule
    ("policy" -> "action") and is required when "policy" is among the strategies.
    """
    strategies = list(strategies)
    s, k = len(strategies), len(trials)
    w = env.num_envs
    if w != s * k:
        raise ValueError(f"rollout: {s} strategies × {k} trials need {s * k} worlds, the env has {w}")
    if POLICY in strategies and policy is None:
        raise ValueError("rollout: the 'policy' strategy needs a policy")
    steps = env.max_steps if steps is None else steps
    dev = env.device
    sim = env.sim

    td = env.reset_to(trials.qpos.repeat(s, 1), trials.qvel.repeat(s, 1), trials.pose_ids.repeat(s))
    sim.set_gain_scale(torch.tensor(gain_scales(strategies), device=dev).repeat_interleave(k))
    state = sim.state
    # "holding the most recent setpoint": the joint angles when the fall begins
    hold = env.action_for_setpoint(state.joint_pos.clone())
    rows = None
    if POLICY in strategies:
        i = strategies.index(POLICY)
        rows = slice(i * k, (i + 1) * k)
        policy.to(dev)  # checkpoints load on the CPU; the env may live on a GPU (sim=warp)

    c = len(env.spec.components)
    peak = torch.zeros(w, steps, c, device=dev)
    mean = torch.zeros(w, steps, c, device=dev)
    lin = torch.zeros(w, steps, device=dev)
    ang = torch.zeros(w, steps, device=dev)
    unstable = torch.zeros(w, dtype=torch.bool, device=dev)
    history: dict[str, list[torch.Tensor]] = {"qpos": [], "qvel": [], "joint_torque": [], "setpoint": []}

    def remember(setpoint: torch.Tensor) -> None:
        if record_states:
            st = sim.state
            for name, value in (("qpos", st.qpos), ("qvel", st.qvel), ("joint_torque", st.joint_torque)):
                history[name].append(value.detach().cpu().clone())
            history["setpoint"].append(setpoint.detach().cpu().clone())

    remember(state.joint_pos)
    for t in range(steps):
        action = hold.clone()
        if rows is not None:
            action[rows] = policy(td[rows].select("policy"))["action"]
        td = env.step(td.set("action", action))["next"]
        st = sim.state
        f = st.contact_force.norm(dim=-1)  # [W, substeps, C]
        peak[:, t] = f.amax(dim=1)
        mean[:, t] = f.mean(dim=1)
        lin[:, t] = st.root_lin_vel.norm(dim=-1)
        ang[:, t] = st.root_ang_vel.norm(dim=-1)
        unstable |= st.unstable.to(dev)
        remember(env.setpoint(action))
        if progress is not None:
            progress.update(1)

    st = sim.state
    poses = trials.pose_ids.to(dev)
    target_quat = env.end_poses.root_quat[poses]
    target_q = env.end_poses.joint_pos[poses]
    traces = {}
    for i, name in enumerate(strategies):
        r = slice(i * k, (i + 1) * k)
        traces[name] = FallTrace(
            peak_force=peak[r],
            mean_force=mean[r],
            root_lin_speed=lin[r],
            root_ang_speed=ang[r],
            final_root_quat=st.root_quat[r],
            final_joint_pos=st.joint_pos[r],
            target_root_quat=target_quat,
            target_joint_pos=target_q,
            unstable=unstable[r],
        )
    out = Rollout(strategies, traces)
    if record_states:
        out.qpos, out.qvel, out.joint_torque, out.setpoint = (torch.stack(history[n]) for n in history)
    return out


# ---- many chunks ------------------------------------------------------------------------


def evaluate(
    env: FallEnv,
    trials: Trials,
    strategies: Sequence[str],
    policy: TensorDictModuleBase | None = None,
    steps: int | None = None,
    show_progress: bool = True,
) -> dict[str, TrialMetrics]:
    """Per-trial metrics of every strategy over all trials, in chunks of the env's worlds."""
    strategies = list(strategies)
    k = env.num_envs // len(strategies)
    n = len(trials)
    chunks = math.ceil(n / k)
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


# ---- mode=eval --------------------------------------------------------------------------


@dataclass
class EvalSetup:
    """What eval and render share: the config the env is built from, the policy (if any)
    and where the end poses come from."""

    config: FallkitConfig  # of the env: the training run's (with a checkpoint), this run's sim
    policy: TensorDictModuleBase | None  # "policy" -> "action"
    checkpoint: str | None
    poses: str  # end-pose source (dataset, pose file or "default")
    split: str

    @property
    def strategies(self) -> list[str]:
        return ([POLICY] if self.policy is not None else []) + list(STRATEGIES)


def prepare(config: FallkitConfig) -> EvalSetup:
    """Load the checkpoint (if any) and decide the end poses named by `config.eval`.

    With a checkpoint the env is built from the training run's config (robot,
    sensitivity, env and reward settings: the observations must match what the
    policy learned on), with this run's simulator settings.
    """
    ev = config.eval
    run_config, policy = config, None
    if config.checkpoint is not None:
        loaded = load_policy(config.checkpoint)
        policy = loaded.module
        trained = loaded.config
        if trained.robot.name != config.robot.name:
            log.warning("evaluating the checkpoint's robot '%s' (robot=%s is ignored)", trained.robot.name, config.robot.name)
        if trained.seed == ev.seed:
            raise ConfigError(
                f"eval.seed: {ev.seed} is the training seed of {config.checkpoint}; "
                "evaluation needs initial states never used in training"
            )
        run_config = trained.model_copy(update={"sim": config.sim})
    poses = ev.poses if ev.poses is not None else run_config.env.poses
    return EvalSetup(run_config, policy, config.checkpoint, poses, ev.split)


def eval_run_config(config: FallkitConfig, seconds: float | None) -> FallkitConfig:
    """The run config an evaluation env is built from (see make_eval_env)."""
    env = config.env
    env_update: dict[str, Any] = {
        "noise": env.noise.model_copy(update={"scale": 0.0}),
        "disturbances": env.disturbances.model_copy(update={"enabled": False}),
        "pose_fraction": 1.0,  # a dataset-size ablation subsamples training poses, never the test split
    }
    if seconds is not None:
        env_update["episode_length"] = seconds
    # Rewards play no part in the metrics: weight 0 switches every term off (not computed),
    # which saves a good part of each env step. blend_time only has to pass the env's check.
    reward = type(config.reward).model_validate(
        {
            **config.reward.model_dump(),
            **{name: 0.0 for name in config.reward.weights()},
            "blend_time": min(config.reward.blend_time, env_update.get("episode_length", env.episode_length)),
        }
    )
    return config.model_copy(update={"env": env.model_copy(update=env_update), "reward": reward})


def make_eval_env(setup: EvalSetup, num_envs: int, seconds: float | None, seed: int) -> FallEnv:
    """The run's FallEnv (fallkit.env.build) for evaluation: no observation noise, no disturbances,
    no reward terms, the whole end-pose split, falls of `seconds` (None: the env's episode length)."""
    cfg = eval_run_config(setup.config, seconds)
    return make_env(cfg, robot_spec(cfg.robot), split=setup.split, seed=seed, num_envs=num_envs, poses=setup.poses)


def evaluate_checkpoint(config: FallkitConfig, run_dir: Path, checkpoint: str | Path) -> dict:
    """Evaluate a checkpoint with `config.eval` into run_dir (the end of a training run)."""
    return run_eval(config.model_copy(update={"checkpoint": str(checkpoint)}), run_dir)


def run_eval(config: FallkitConfig, run_dir: Path) -> dict:
    """`mode=eval`: evaluate, write the results into run_dir, print the table."""
    ev = config.eval
    torch.set_num_threads(1)  # the physics threads are MuJoCo's (2 torch threads beside them measured 1.5-1.8x slower)
    setup = prepare(config)
    strategies = setup.strategies
    k, chunks = chunking(ev.trials, len(strategies), config.sim.num_envs)
    env = make_eval_env(setup, len(strategies) * k, ev.seconds, ev.seed)
    trials = draw_trials(env, ev.trials, ev.seed)
    log.info(
        "eval %s: %d trials × %s, %d chunk(s) of %d worlds, %.2f s falls",
        env.spec.name, ev.trials, ", ".join(strategies), chunks, env.num_envs, env.max_steps * env.dt,
    )  # fmt: skip
    t0 = time.perf_counter()
    results = evaluate(env, trials, strategies, setup.policy)
    info = {
        "robot": env.spec.name,
        "checkpoint": setup.checkpoint,
        "trials": ev.trials,
        "seconds": env.max_steps * env.dt,
        "seed": ev.seed,
        "poses": f"{setup.poses} ({_split_note(setup)}{len(env.end_poses)} poses)",
        "elapsed": time.perf_counter() - t0,
    }
    summary = write_results(results, env.spec.component_names, info, Path(run_dir))
    print()
    print(text_table(summary))
    print(f"\n{ev.trials} falls × {len(strategies)} strategies in {info['elapsed']:.1f} s; results in {run_dir}/eval.md")
    return summary


def _split_note(setup: EvalSetup) -> str:
    """Pose files have no splits; datasets do."""
    artist = setup.poses == "artist" or Path(setup.poses).suffix in (".yaml", ".yml")
    return "" if artist else f"{setup.split} split, "


def write_results(results: dict[str, TrialMetrics], components: list[str], info: dict, run_dir: Path) -> dict:
    """eval.json, eval.md, eval_trials.npz and the plots; returns the eval.json object."""
    summary = {
        name: {"gain_scale": gain_scales([name])[0], **summarize_trials(m, components)} for name, m in results.items()
    }
    (run_dir / "eval.json").write_text(json.dumps(summary, indent=2))
    np.savez_compressed(
        run_dir / "eval_trials.npz",
        components=np.array(components),
        **{f"{s}/{key}": v for s, m in results.items() for key, v in m.arrays().items()},
    )
    title = f"{info['robot']}: {info['trials']} falls per strategy"
    figures = plots.plot_all(results, components, run_dir, title)
    (run_dir / "eval.md").write_text(markdown_report(summary, info, [f.name for f in figures]))
    unstable = {n: s["unstable_trials"] for n, s in summary.items() if s["unstable_trials"]}
    if unstable:
        log.warning("falls restarted by the simulator (unstable), per strategy: %s", unstable)
    return summary


# ---- reports ------------------------------------------------------------------------------

_METRICS = [
    ("max_impact_force", "max impact [N]", "{:.0f}"),
    ("mean_impact_force", "mean impact [N]", "{:.0f}"),
    ("fall_mean_impact_force", "mean impact, fall phase [N]", "{:.0f}"),
    ("mroe", "MROE [rad]", "{:.2f}"),
    ("mje", "MJE [rad]", "{:.2f}"),
]


def text_table(summary: dict) -> str:
    """A compact terminal table: mean ± std (median / p95) of each metric."""
    head = f"{'strategy':12s}" + "".join(f"{label:>30s}" for _, label, _ in _METRICS)
    lines = [head]
    for name, s in summary.items():
        cells = []
        for key, _, fmt in _METRICS:
            v = s[key]
            cells.append(f"{fmt.format(v['mean'])} ± {fmt.format(v['std'])} ({fmt.format(v['median'])}/{fmt.format(v['p95'])})")
        lines.append(f"{name:12s}" + "".join(f"{c:>30s}" for c in cells))
    lines.append("cells: mean ± std (median/p95) over trials")
    return "\n".join(lines)


def markdown_report(summary: dict, info: dict, figures: list[str]) -> str:
    """eval.md: what was run, the metric table, per-component figures, the plots."""
    names = list(summary)
    out = [f"# Evaluation: {info['robot']}", ""]
    out += [
        f"- policy: `{info['checkpoint']}`" if info["checkpoint"] else "- policy: none (standard strategies only)",
        f"- {info['trials']} falls per strategy, {info['seconds']:.2f} s each, "
        f"the same initial states and end poses for every strategy (seed {info['seed']})",
        f"- end poses: {info['poses']}",
        f"- took {info['elapsed']:.1f} s",
        "",
        "## Metrics (paper Sec. V-B)",
        "",
        "mean ± std, then median / 95th percentile, over trials.",
        "",
        "| strategy | " + " | ".join(label for _, label, _ in _METRICS) + " | unstable |",
        "|---|" + "---|" * (len(_METRICS) + 1),
    ]
    for n in names:
        s = summary[n]
        cells = []
        for key, _, fmt in _METRICS:
            v = s[key]
            cells.append(
                f"{fmt.format(v['mean'])} ± {fmt.format(v['std'])}<br>{fmt.format(v['median'])} / {fmt.format(v['p95'])}"
            )
        out.append(f"| {n} | " + " | ".join(cells) + f" | {s['unstable_trials']} |")
    out += [
        "",
        "- max impact: the largest contact force on any component during the fall (every physics substep).",
        "- mean impact: the maximum over components of the time-mean contact force on that component.",
        "  Once the robot lies still this is dominated by its resting weight, so the fall-phase column",
        "  averages only over the steps before the robot first comes to rest.",
        "- MROE: geodesic distance between the target root orientation, turned about the vertical to",
        "  match the robot, and the root orientation at the last step. MJE: mean |q − q̂| at the last step.",
        "",
        "## Per component: max impact force [N], median / 95th percentile",
        "",
    ]
    comps = list(summary[names[0]]["per_component"])
    out += ["| strategy | " + " | ".join(comps) + " |", "|---|" + "---|" * len(comps)]
    for n in names:
        pc = summary[n]["per_component"]
        out.append(
            f"| {n} | "
            + " | ".join(f"{pc[c]['max_impact_force']['median']:.0f} / {pc[c]['max_impact_force']['p95']:.0f}" for c in comps)
            + " |"
        )
    out += ["", "## Plots", ""] + [f"![{f}]({f})" for f in figures] + [""]
    return "\n".join(out)
