"""The paper's evaluation metrics (Sec. V-B "Metrics") as small pure functions.

Every function takes recorded trajectories of a batch of falls and returns one
figure per trial (or per trial and component); `summarize` aggregates trials.
Shapes: N trials, T recorded time samples, C components, J joints. Forces are
contact-force magnitudes |f_c| in newtons, summed per component (the net force
a component receives, as the impact reward sees it).

- max impact force   max over time and components of |f_c|
- mean impact force  max over components of the time-mean of |f_c|
- fall-phase mean    the same, averaged only over the steps before the robot
                     first comes to rest (the literal mean is dominated by the
                     robot's resting weight once it lies still)
- MROE               geodesic distance between the yaw-aligned target root
                     orientation and the final root orientation
- MJE                mean absolute joint error at the final step
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
import torch

from fallkit.rotations import geodesic_angle, normalize, yaw_align

# A fall is over once the root moves slower than this for REST_HOLD_STEPS steps.
# Measured on biped20 lying still after a fall: root speeds ~1e-3 m/s, 1e-2 rad/s.
REST_LIN_SPEED = 0.05  # [m/s]
REST_ANG_SPEED = 0.2  # [rad/s]
REST_HOLD_STEPS = 5  # 0.1 s at 50 Hz: a bounce's turning point is not rest


def max_impact_force(force: torch.Tensor) -> torch.Tensor:
    """Largest contact force on any component during the rollout: [N, T, C] -> [N]."""
    return force.amax(dim=(1, 2))


def component_max_force(force: torch.Tensor) -> torch.Tensor:
    """Largest contact force on each component during the rollout: [N, T, C] -> [N, C]."""
    return force.amax(dim=1)


def component_mean_force(force: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Time-mean contact force on each component, over the samples where `mask` [N, T] is true.

    [N, T, C] -> [N, C]. A trial with an empty mask averages over nothing and gets 0.
    """
    if mask is None:
        return force.mean(dim=1)
    m = mask.to(force.dtype).unsqueeze(-1)
    return (force * m).sum(dim=1) / m.sum(dim=1).clamp(min=1.0)


def mean_impact_force(force: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """The maximum over components of the mean contact force on that component: [N, T, C] -> [N]."""
    return component_mean_force(force, mask).amax(dim=1)


def rest_step(
    root_lin_speed: torch.Tensor,
    root_ang_speed: torch.Tensor,
    lin_tol: float = REST_LIN_SPEED,
    ang_tol: float = REST_ANG_SPEED,
    hold: int = REST_HOLD_STEPS,
) -> torch.Tensor:
    """First step at which the robot comes to rest: [N, T] speeds -> [N] step index (T if never).

    At rest = root linear speed < lin_tol and angular speed < ang_tol for `hold`
    consecutive steps; the index is the first of those steps.
    """
    n, t = root_lin_speed.shape
    still = ((root_lin_speed < lin_tol) & (root_ang_speed < ang_tol)).to(torch.float32)
    if t < hold:
        return torch.full((n,), t, dtype=torch.long, device=still.device)
    # windows[:, i] = number of still steps in [i, i + hold)
    windows = torch.nn.functional.avg_pool1d(still.unsqueeze(1), hold, stride=1).squeeze(1) * hold
    rested = windows > hold - 0.5
    first = rested.to(torch.float32).argmax(dim=1)
    return torch.where(rested.any(dim=1), first, torch.full_like(first, t))


def fall_phase_mask(rest: torch.Tensor, steps: int) -> torch.Tensor:
    """[N] rest step -> [N, steps] mask of the steps before rest (at least the first step)."""
    t = torch.arange(steps, device=rest.device)
    return t.unsqueeze(0) < rest.clamp(min=1).unsqueeze(1)


def fall_mean_impact_force(force: torch.Tensor, rest: torch.Tensor) -> torch.Tensor:
    """Mean impact force over the fall phase only (steps before `rest` [N]): [N, T, C] -> [N]."""
    return mean_impact_force(force, fall_phase_mask(rest, force.shape[1]))


def mroe(root_quat: torch.Tensor, target_quat: torch.Tensor) -> torch.Tensor:
    """Root orientation error [rad] at the final step: [N, 4], [N, 4] -> [N].

    The geodesic distance between the target orientation turned about the
    global yaw axis to match the robot (the best-matching yaw, so it is defined
    for heading-less poses such as lying face up too) and the robot's final
    orientation. Computed on renormalised float64 quaternions: acos near 1 turns
    float32 rounding (|q| = 1 ± 1e-7) into errors of 1e-4 rad.
    """
    q, target = normalize(root_quat.double()), normalize(target_quat.double())
    return geodesic_angle(yaw_align(target, q), q)


def mje(joint_pos: torch.Tensor, target_joint_pos: torch.Tensor) -> torch.Tensor:
    """Mean absolute joint error [rad] over all joints at the final step: [N, J], [N, J] -> [N]."""
    return (joint_pos - target_joint_pos).abs().mean(dim=-1)


# ---- one batch of falls --------------------------------------------------------------


@dataclass
class FallTrace:
    """What a batch of N falls recorded, enough for every metric.

    `peak_force` is the worst physics substep of each policy step (the force
    the maximum sees); `mean_force` the mean over the substeps (so time-means
    weigh every physics step equally).
    """

    peak_force: torch.Tensor  # [N, T, C] max over substeps of |f_c| [N]
    mean_force: torch.Tensor  # [N, T, C] mean over substeps of |f_c| [N]
    root_lin_speed: torch.Tensor  # [N, T] [m/s]
    root_ang_speed: torch.Tensor  # [N, T] [rad/s]
    final_root_quat: torch.Tensor  # [N, 4]
    final_joint_pos: torch.Tensor  # [N, J]
    target_root_quat: torch.Tensor  # [N, 4]
    target_joint_pos: torch.Tensor  # [N, J]
    unstable: torch.Tensor  # [N] bool: the simulator found the world unstable and reset it


@dataclass
class TrialMetrics:
    """Per-trial figures; concatenate batches with `cat`."""

    max_impact_force: np.ndarray  # [N]
    mean_impact_force: np.ndarray  # [N]
    fall_mean_impact_force: np.ndarray  # [N]
    mroe: np.ndarray  # [N]
    mje: np.ndarray  # [N]
    rest_time: np.ndarray  # [N] seconds until the robot first came to rest (episode length if never)
    component_max_force: np.ndarray  # [N, C]
    component_mean_force: np.ndarray  # [N, C]
    component_fall_mean_force: np.ndarray  # [N, C]
    unstable: np.ndarray  # [N] bool: the fall was restarted by the simulator (its figures are suspect)

    def __len__(self) -> int:
        return len(self.max_impact_force)

    @staticmethod
    def cat(parts: list["TrialMetrics"]) -> "TrialMetrics":
        return TrialMetrics(**{f.name: np.concatenate([getattr(p, f.name) for p in parts]) for f in fields(TrialMetrics)})

    def take(self, index: np.ndarray | slice) -> "TrialMetrics":
        return TrialMetrics(**{f.name: getattr(self, f.name)[index] for f in fields(TrialMetrics)})

    def arrays(self) -> dict[str, np.ndarray]:
        return {f.name: getattr(self, f.name) for f in fields(TrialMetrics)}


def trial_metrics(trace: FallTrace, policy_dt: float) -> TrialMetrics:
    """Every per-trial metric of a batch of recorded falls."""
    rest = rest_step(trace.root_lin_speed, trace.root_ang_speed)
    fall = fall_phase_mask(rest, trace.peak_force.shape[1])

    def np_(t: torch.Tensor) -> np.ndarray:
        return t.detach().cpu().double().numpy()

    return TrialMetrics(
        max_impact_force=np_(max_impact_force(trace.peak_force)),
        mean_impact_force=np_(mean_impact_force(trace.mean_force)),
        fall_mean_impact_force=np_(mean_impact_force(trace.mean_force, fall)),
        mroe=np_(mroe(trace.final_root_quat, trace.target_root_quat)),
        mje=np_(mje(trace.final_joint_pos, trace.target_joint_pos)),
        rest_time=np_(rest.to(torch.float64) * policy_dt),
        component_max_force=np_(component_max_force(trace.peak_force)),
        component_mean_force=np_(component_mean_force(trace.mean_force)),
        component_fall_mean_force=np_(component_mean_force(trace.mean_force, fall)),
        unstable=trace.unstable.detach().cpu().numpy().astype(bool),
    )


# ---- aggregation ------------------------------------------------------------------------


def summarize(values: np.ndarray) -> dict[str, float]:
    """mean, std, median and 95th percentile of per-trial values."""
    v = np.asarray(values, dtype=np.float64)
    if v.size == 0:  # every trial was unstable: nothing to summarize, and the table says so
        return dict.fromkeys(("mean", "std", "median", "p95"), float("nan"))
    return {
        "mean": float(v.mean()),
        "std": float(v.std()),
        "median": float(np.median(v)),
        "p95": float(np.percentile(v, 95)),
    }


def summarize_trials(m: TrialMetrics, component_names: list[str]) -> dict:
    """The eval.json object of one strategy. Falls the simulator restarted (unstable) are counted
    but left out of every statistic: their figures mix two falls."""
    trials, unstable = len(m), int(m.unstable.sum())
    m = m.take(~m.unstable)
    return {
        "trials": trials,
        "unstable_trials": unstable,
        "max_impact_force": summarize(m.max_impact_force),
        "mean_impact_force": summarize(m.mean_impact_force),
        "fall_mean_impact_force": summarize(m.fall_mean_impact_force),
        "mroe": summarize(m.mroe),
        "mje": summarize(m.mje),
        "rest_time": summarize(m.rest_time),
        "per_component": {
            c: {
                "max_impact_force": summarize(m.component_max_force[:, k]),
                "mean_impact_force": summarize(m.component_mean_force[:, k]),
                "fall_mean_impact_force": summarize(m.component_fall_mean_force[:, k]),
            }
            for k, c in enumerate(component_names)
        },
    }
