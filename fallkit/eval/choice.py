"""`eval.poses=auto`: each fall's end pose chosen from a candidate set at the moment the fall begins.

The paper's end poses are chosen by hand, without regard to the state the fall starts in; a
pose the robot is already heading for is reached more easily and, perhaps, more softly. Two
scorers rank the candidates of every fall (docs/end_pose_choice.md):

- `critic`: the trained critic's value V(s, g) of the fall's first state s with each candidate
  goal g substituted into its observation (the goal columns of the noiseless actor part,
  `fallkit.env.observations`): the return the training expects toward that goal, impact and
  tracking rewards together. One batched forward pass scores a group of falls × every candidate;
  the argmax per fall is chosen. The critic observes privileged state (body heights and
  velocities), so this scorer lives in simulation only.
- `heading`: the candidate lying closest to where the fall is heading, its capture point
  (`fallkit.pose_choice`, numpy): from what a robot's estimator provides; the deployed
  `FallController.choose_end_pose` runs the same code.

The choice changes the end-pose ids of the trials only: every strategy still falls from the
same initial states toward the same (chosen) end poses, and the random assignment it is
compared with is `draw_trials`' shuffled cycle through the same candidates, on the same falls.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch
from torch import nn

from fallkit.env.fall_env import FallEnv
from fallkit.env.observations import actor_slices
from fallkit.errors import CheckpointError, ConfigError
from fallkit.eval.metrics import TrialMetrics
from fallkit.eval.rollout import Trials
from fallkit.pose_choice import PIVOT_HEIGHT, choose_by_heading, ground_sides, side_counts, side_rows
from fallkit.poses.end_pose_set import EndPoseSet
from fallkit.rotations import gravity_in_frame, quat_rotate_inverse, tilt_quat

# Observations per critic call: [rows, Dc] float32 is ~100 MB for biped20 (Dc = 404), so 256 falls ×
# 2000 candidates take 8 calls; one call for all would need 0.8 GB.
CRITIC_ROWS = 1 << 16

# (metric, label, format) of the auto-vs-random comparison, in the order of the question
COMPARED = (
    ("mje", "MJE [rad]", "{:.3f}"),
    ("mroe", "MROE [rad]", "{:.2f}"),
    ("max_impact_force", "max impact [N]", "{:.0f}"),
    ("fall_mean_impact_force", "fall-phase mean impact [N]", "{:.1f}"),
)


@dataclass
class PoseChoice:
    """How eval.poses=auto chooses (eval.scorer, eval.candidate_side, eval.heading_pivot_height), with the
    checkpoint's critic for scorer=critic."""

    scorer: str  # "critic" | "heading"
    sides: list[str] | None = None
    critic: nn.Module | None = None  # [..., Dc] -> [..., heads] (a value per reward term: summed)
    pivot_height: float = PIVOT_HEIGHT

    def describe(self) -> str:
        if self.scorer == "critic":
            return "critic: argmax over the candidates of the checkpoint's value V(s, g) at the fall's first state"
        pendulum = f"{self.pivot_height:g} m pendulum"
        return f"heading: the candidate lying closest to where the fall heads, its capture point ({pendulum})"


def restrict(poses: EndPoseSet, sides: list[str] | None, source: str) -> EndPoseSet:
    """The candidates lying on one of `sides` (all for None); none left is a ConfigError listing the sides there are."""
    if not sides:
        return poses
    quat = poses.root_quat.detach().cpu().double().numpy()
    rows = side_rows(quat, sides)
    if len(rows) == 0:
        there = ", ".join(f"{s} {n}" for s, n in side_counts(quat).items())
        raise ConfigError(
            f"eval.candidate_side={','.join(sides)}: none of the {len(poses)} candidates of {source} lies on it; "
            f"they lie on: {there}"
        )
    index = torch.as_tensor(rows, device=poses.joint_pos.device)
    names = [poses.names[i] for i in rows] if poses.names else []
    return EndPoseSet(poses.robot, poses.joint_names, poses.joint_pos[index], poses.root_quat[index], names)


@dataclass
class StartStates:
    """What every fall begins with: the critic observation and what a robot's estimator gives."""

    critic: torch.Tensor  # [N, Dc] (the env's device)
    root_quat: np.ndarray  # [N, 4] world frame
    lin_vel: np.ndarray  # [N, 3] base frame [m/s]


@torch.no_grad()
def start_states(env: FallEnv, trials: Trials) -> StartStates:
    """Reset the env's worlds to the trials' initial states (in chunks of its worlds) and read them.

    The observation at the reset is the one the policy and critic see when the fall begins; the
    end pose it was reset toward is replaced by each candidate's when scoring.
    """
    n, w = len(trials), env.num_envs
    critic, quat, lin = [], [], []
    for start in range(0, n, w):
        index = torch.arange(start, start + w).clamp(max=n - 1)  # the last chunk repeats its last trial
        real = min(w, n - start)
        td = env.reset_to(trials.qpos[index], trials.qvel[index], trials.pose_ids[index])
        st = env.sim.state
        critic.append(td["critic"][:real].clone())
        quat.append(st.root_quat[:real].double().cpu())
        lin.append(quat_rotate_inverse(st.root_quat[:real], st.root_lin_vel[:real]).double().cpu())
    return StartStates(torch.cat(critic), *(torch.cat(x).numpy() for x in (quat, lin)))


@torch.no_grad()
def critic_values(
    critic: nn.Module, critic_obs: torch.Tensor, goal_root_quat: torch.Tensor, goal_joint_pos: torch.Tensor,
    columns: dict[str, slice], rows: int = CRITIC_ROWS,
) -> torch.Tensor:  # fmt: skip
    """V(s, g) [N, P]: every fall's first critic observation [N, Dc] with each candidate's goal substituted.

    goal_root_quat [P, 4] is the candidates' tilt (the heading-free goal the env observes, tilt_quat),
    goal_joint_pos [P, J]; `columns` names the goal's columns (actor_slices: the critic observation
    begins with the noiseless actor observation). Falls go through the critic in groups of
    rows // P, all candidates of a fall in the same call.
    """
    n, p = critic_obs.shape[0], goal_root_quat.shape[0]
    width = _input_width(critic)
    if width is not None and width != critic_obs.shape[1]:
        raise CheckpointError(
            f"the checkpoint's critic reads {width} inputs, this env's critic observation has {critic_obs.shape[1]}"
        )
    per = max(1, rows // p)
    out = torch.empty(n, p, device=critic_obs.device)
    goal_gravity = gravity_in_frame(goal_root_quat) if "goal_gravity" in columns else None  # env.observe_gravity
    for i in range(0, n, per):
        obs = critic_obs[i : i + per].unsqueeze(1).repeat(1, p, 1)  # [b, P, Dc]
        obs[..., columns["goal_root_quat"]] = goal_root_quat
        obs[..., columns["goal_joint_pos"]] = goal_joint_pos
        if goal_gravity is not None:
            obs[..., columns["goal_gravity"]] = goal_gravity
        out[i : i + per] = critic(obs).sum(-1)  # a critic with a value per reward term: V(s, g) is their sum
    return out


def _input_width(critic: nn.Module) -> int | None:
    norm = getattr(critic, "norm", None)
    return int(norm.mean.shape[0]) if norm is not None else None


def candidate_values(env: FallEnv, critic: nn.Module, starts: StartStates) -> torch.Tensor:
    """V(s, g) [N, P] of every fall against every end pose of the env, goals encoded exactly as the env does."""
    poses = env.end_poses
    goal_tilt = tilt_quat(poses.root_quat.to(torch.float32))  # FallEnv._goal_tilt
    critic.to(env.device)
    return critic_values(critic, starts.critic, goal_tilt, poses.joint_pos.to(torch.float32), actor_slices(env.spec, env.observes_sensitivity, env.observes_gravity))


def choose_end_poses(env: FallEnv, trials: Trials, choice: PoseChoice) -> Trials:
    """The same falls with each end pose chosen from the env's poses by `choice` (rows of env.end_poses)."""
    starts = start_states(env, trials)
    if choice.scorer == "critic":
        if choice.critic is None:
            raise ConfigError("eval.scorer=critic needs the checkpoint's critic: give checkpoint=<run dir>")
        ids = candidate_values(env, choice.critic, starts).argmax(dim=1).cpu()
    else:
        quat = env.end_poses.root_quat.detach().cpu().double().numpy()
        ids = torch.from_numpy(choose_by_heading(starts.root_quat, starts.lin_vel, quat, choice.pivot_height))
    return Trials(trials.qpos, trials.qvel, ids.long())


# ---- chosen vs random ---------------------------------------------------------------------


def compare(
    random: dict[str, TrialMetrics], chosen: dict[str, TrialMetrics], random_ids: torch.Tensor,
    chosen_ids: torch.Tensor, poses: EndPoseSet, choice: PoseChoice, source: str,
) -> dict:  # fmt: skip
    """eval.json's `end_pose_choice`: per strategy and metric the mean under random assignment and
    under the choice, over the falls stable in both, with the paired difference and its 95 % interval."""
    strategies = {}
    for name, b in chosen.items():
        a = random[name]
        ok = ~(a.unstable | b.unstable)
        row: dict = {"trials": int(ok.sum())}
        for key, _, _ in COMPARED:
            x, y = getattr(a, key)[ok], getattr(b, key)[ok]
            d = y - x
            half = 1.96 * float(d.std(ddof=1)) / math.sqrt(len(d)) if len(d) > 1 else float("nan")
            mean = float(d.mean()) if len(d) else float("nan")
            row[key] = {
                "random": float(x.mean()) if len(x) else float("nan"),
                "auto": float(y.mean()) if len(y) else float("nan"),
                "diff": mean,
                "diff_ci95": [mean - half, mean + half],
            }
        strategies[name] = row
    sides = ground_sides(poses.root_quat.detach().cpu().double().numpy()[chosen_ids.numpy()])
    return {
        "label": "chosen (auto) vs random assignment on the same falls",
        "scorer": choice.scorer,
        "how": choice.describe(),
        "candidates": source,
        "candidate_count": len(poses),
        "candidate_side": choice.sides,
        "distinct_chosen": int(torch.unique(chosen_ids).numel()),
        "distinct_random": int(torch.unique(random_ids).numel()),
        "chosen_sides": {s: float((sides == s).mean()) for s in dict.fromkeys(sides.tolist())},
        "strategies": strategies,
    }


def choice_markdown(c: dict, label: Callable[[str], str] = str) -> list[str]:
    """eval.md's section on the comparison (`compare`'s object); `label` names a strategy in the table."""
    sides = ", ".join(f"{s} {share:.0%}" for s, share in sorted(c["chosen_sides"].items(), key=lambda kv: -kv[1]))
    out = [
        "## End pose chosen (auto) vs random assignment on the same falls",
        "",
        f"- scorer: {c['how']}",
        f"- candidates: {c['candidates']}"
        + (f", lying on {'/'.join(c['candidate_side'])}" if c["candidate_side"] else ""),
        f"- poses chosen: {c['distinct_chosen']} distinct (random assignment: {c['distinct_random']}); sides: {sides}",
        "- the tables above are the chosen poses'; random: the shuffled cycle through the same candidates that a",
        "  fixed eval.poses gives. Cells: random → auto, then the paired mean difference (auto − random) with its",
        "  95 % interval. The standard strategies ignore the end pose: their impacts cannot change, their MROE",
        "  and MJE say how close the chosen poses lie to where an uncontrolled fall ends.",
        "",
        "| strategy | " + " | ".join(lbl for _, lbl, _ in COMPARED) + " |",
        "|---|" + "---|" * len(COMPARED),
    ]
    for name, row in c["strategies"].items():
        cells = []
        for key, _, fmt in COMPARED:
            m = row[key]
            lo, hi = m["diff_ci95"]
            cells.append(
                f"{fmt.format(m['random'])} → {fmt.format(m['auto'])}<br>{m['diff']:+.3g} [{lo:+.3g}, {hi:+.3g}]"
            )
        out.append(f"| {label(name)} | " + " | ".join(cells) + " |")
    return out + [""]


def choice_line(c: dict, name: str = "policy") -> str:
    """One line for the terminal: the policy's (or a strategy's) means, random → auto."""
    row = c["strategies"][name]
    cells = ", ".join(
        f"{lbl.split(' [')[0]} {fmt.format(row[k]['random'])} → {fmt.format(row[k]['auto'])}"
        for k, lbl, fmt in COMPARED[:3]
    )
    return f"end pose chosen by {c['scorer']} vs random, {name}: {cells}"
