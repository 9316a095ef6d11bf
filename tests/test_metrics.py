"""The paper's metrics on hand-built trajectories with known answers."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from fallkit.eval import metrics
from fallkit.rotations import geodesic_angle, quat_from_euler, quat_mul


def _euler(roll: float, pitch: float, yaw: float) -> torch.Tensor:
    t = lambda v: torch.tensor([v], dtype=torch.float64)  # noqa: E731
    return quat_from_euler(t(roll), t(pitch), t(yaw))


def test_max_impact_force_is_the_largest_force_on_any_component():
    force = torch.full((2, 5, 3), 10.0)
    force[0, 3, 2] = 500.0  # trial 0: one spike on component 2
    force[1, 0, 0] = 42.0
    assert metrics.max_impact_force(force).tolist() == [500.0, 42.0]
    assert metrics.component_max_force(force)[0].tolist() == [10.0, 10.0, 500.0]


def test_mean_impact_force_is_the_max_over_components_of_the_time_mean():
    # component 0: constant 100 N; component 1: a single 600 N spike over 4 steps (mean 150 N)
    force = torch.zeros(1, 4, 2)
    force[0, :, 0] = 100.0
    force[0, 2, 1] = 600.0
    assert metrics.component_mean_force(force)[0].tolist() == [100.0, 150.0]
    assert metrics.mean_impact_force(force).item() == 150.0  # not the mean of maxima (350) nor 125
    assert metrics.max_impact_force(force).item() == 600.0


def test_rest_is_the_first_step_of_a_long_enough_still_window():
    hold = metrics.REST_HOLD_STEPS
    lin = torch.ones(3, 20)
    ang = torch.zeros(3, 20)
    lin[0, 2] = 0.0  # trial 0: a single still step (a bounce's turning point) ...
    lin[0, 9:] = 0.0  # ... then at rest from step 9
    lin[1, 20 - hold + 1 :] = 0.0  # trial 1: still for fewer than `hold` steps at the end: never at rest
    lin[2, :] = 0.0
    ang[2, :6] = 1.0  # trial 2: the root keeps turning until step 6
    assert metrics.rest_step(lin, ang).tolist() == [9, 20, 6]


def test_fall_phase_mean_leaves_out_the_resting_weight():
    weight = 159.0
    force = torch.zeros(1, 10, 2)
    force[0, :4, 0] = torch.tensor([0.0, 800.0, 400.0, 200.0])  # the fall: 4 steps
    force[0, 4:, 0] = weight  # lying still on component 0
    rest = torch.tensor([4])
    assert metrics.fall_mean_impact_force(force, rest).item() == pytest.approx(350.0)
    assert metrics.mean_impact_force(force).item() == pytest.approx((1400.0 + 6 * weight) / 10)
    # a fall that never comes to rest averages over every step
    assert metrics.fall_mean_impact_force(force, torch.tensor([10])).item() == pytest.approx(metrics.mean_impact_force(force).item())


def test_mroe_is_the_yaw_aligned_geodesic_distance():
    lying = _euler(0.0, math.pi / 2, 0.3)  # target: lying on the back, some heading
    # the robot lies 0.25 rad further pitched, with a different heading: error 0.25 rad
    final = quat_mul(_euler(0.0, 0.0, 2.0), _euler(0.0, math.pi / 2 + 0.25, 0.0))
    assert metrics.mroe(final, lying).item() == pytest.approx(0.25, abs=1e-9)
    # heading alone is no error; the plain geodesic distance would be large
    turned = quat_mul(_euler(0.0, 0.0, 1.4), lying)
    assert metrics.mroe(turned, lying).item() == pytest.approx(0.0, abs=1e-7)
    assert geodesic_angle(turned, lying).item() == pytest.approx(1.4)


def test_mroe_is_the_minimum_geodesic_distance_over_yaw():
    g = torch.Generator().manual_seed(3)
    a = torch.nn.functional.normalize(torch.randn(16, 4, generator=g, dtype=torch.float64), dim=-1)
    b = torch.nn.functional.normalize(torch.randn(16, 4, generator=g, dtype=torch.float64), dim=-1)
    yaw = torch.linspace(-math.pi, math.pi, 4001, dtype=torch.float64)
    z = torch.zeros_like(yaw)
    turns = quat_from_euler(z, z, yaw)  # [Y, 4]
    brute = geodesic_angle(quat_mul(turns[:, None], b[None]), a[None].expand(len(yaw), -1, -1)).min(dim=0).values
    assert torch.allclose(metrics.mroe(a, b), brute, atol=2e-3)
    assert (metrics.mroe(a, b) <= brute + 1e-9).all()


def test_mje_is_the_mean_absolute_joint_error():
    target = torch.tensor([[0.5, -0.2, 0.0, 1.0]])
    q = target + torch.tensor([[0.1, -0.3, 0.2, 0.0]])
    assert metrics.mje(q, target).item() == pytest.approx(0.15)


def test_summarize_mean_std_median_p95():
    s = metrics.summarize(np.arange(1, 101, dtype=float))
    assert s == pytest.approx({"mean": 50.5, "std": np.std(np.arange(1, 101)), "median": 50.5, "p95": 95.05})
    empty = metrics.summarize(np.array([]))  # every trial unstable: NaN, shown as such, not an exception
    assert all(np.isnan(v) for v in empty.values())


def test_trial_metrics_of_a_hand_built_trace():
    n, t, c, j = 2, 12, 3, 4
    peak = torch.zeros(n, t, c)
    mean = torch.zeros(n, t, c)
    peak[0, 1, 1] = 900.0
    mean[0, 1, 1] = 600.0
    mean[:, 5:, 0] = 159.0  # both lie still from step 5 on
    lin = torch.ones(n, t)
    lin[:, 5:] = 0.0
    ang = torch.zeros(n, t)
    target_q = torch.zeros(n, j)
    trace = metrics.FallTrace(
        peak_force=peak,
        mean_force=mean,
        root_lin_speed=lin,
        root_ang_speed=ang,
        final_root_quat=torch.cat([_euler(0.1, 0.0, 0.0), _euler(0.0, 0.0, 1.0)]).float(),
        final_joint_pos=torch.tensor([[0.4, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0]]),
        target_root_quat=torch.cat([_euler(0.0, 0.0, 0.0), _euler(0.0, 0.0, 0.0)]).float(),
        target_joint_pos=target_q,
        unstable=torch.tensor([False, True]),
    )
    m = metrics.trial_metrics(trace, policy_dt=0.02)
    assert m.max_impact_force.tolist() == [900.0, 0.0]
    assert m.mean_impact_force.tolist() == pytest.approx([159.0 * 7 / 12, 159.0 * 7 / 12])
    assert m.fall_mean_impact_force.tolist() == pytest.approx([600.0 / 5, 0.0])
    assert m.rest_time.tolist() == pytest.approx([0.1, 0.1])
    assert m.mroe == pytest.approx([0.1, 0.0], abs=1e-6)
    assert m.mje == pytest.approx([0.1, 0.0])
    assert m.component_max_force.shape == (n, c)
    assert m.unstable.tolist() == [False, True]
    both = metrics.TrialMetrics.cat([m, m.take(slice(0, 1))])
    assert len(both) == 3 and both.max_impact_force.tolist() == [900.0, 0.0, 900.0]
    summary = metrics.summarize_trials(m, ["pelvis", "legs", "head"])
    # the unstable trial is counted, and left out of every statistic (it mixes two falls)
    assert summary["trials"] == 2 and summary["unstable_trials"] == 1
    assert summary["max_impact_force"]["mean"] == 900.0 and summary["mje"]["mean"] == pytest.approx(0.1)
    assert summary["per_component"]["legs"]["max_impact_force"]["median"] == pytest.approx(900.0)
    none = metrics.summarize_trials(m.take(slice(1, 2)), ["pelvis", "legs", "head"])
    assert none["unstable_trials"] == 1 and np.isnan(none["max_impact_force"]["mean"])
