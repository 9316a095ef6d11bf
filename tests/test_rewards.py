"""Reward terms (paper Table I) against hand computations on known states."""

from __future__ import annotations

import math
import textwrap

import pytest
import torch

from fallkit import registry
from fallkit.config import BUILTIN_TERMS, ConfigError, RewardConfig, validate
from fallkit.env.rewards import RewardContext, RewardSum
from fallkit.env.rewards.impact import impact, root_acc
from fallkit.env.rewards.regularization import action_acc, action_rate, joint_acc, offset, torques
from fallkit.env.rewards.tracking import blend, joints, orientation
from fallkit.rotations import quat_from_euler
from fallkit.sim.base import SimState

N, S, C, J = 2, 4, 5, 3
IDENTITY = torch.tensor([1.0, 0.0, 0.0, 0.0])


def make_state(**fields) -> SimState:
    zeros = {
        "qpos": torch.zeros(N, 7 + J), "qvel": torch.zeros(N, 6 + J), "root_pos": torch.zeros(N, 3),
        "root_quat": IDENTITY.repeat(N, 1), "root_lin_vel": torch.zeros(N, 3), "root_ang_vel": torch.zeros(N, 3),
        "root_lin_acc": torch.zeros(N, 3), "joint_pos": torch.zeros(N, J), "joint_vel": torch.zeros(N, J),
        "joint_acc": torch.zeros(N, J), "joint_torque": torch.zeros(N, J), "contact_force": torch.zeros(N, S, C, 3),
        "unstable": torch.zeros(N, dtype=torch.bool),
    }  # fmt: skip
    zeros.update(fields)
    return SimState(**zeros)


def make_ctx(state: SimState | None = None, **fields) -> RewardContext:
    ctx = dict(
        state=state or make_state(),
        action=torch.zeros(N, J),
        last_action=torch.zeros(N, J),
        last_last_action=torch.zeros(N, J),
        target_root_quat=IDENTITY.repeat(N, 1),
        target_joint_pos=torch.zeros(N, J),
        sensitivity=torch.tensor([1.0, 1.0, 2.0, 3.0, 4.0]),  # biped20: pelvis, legs, elbows, shoulders, head
        time=torch.full((N,), 10.0),
        blend=torch.ones(N),
        force_unit=1000.0,
        force_clip=10.0,
        dt=0.02,
    )
    ctx.update(fields)
    return RewardContext(**ctx)


def test_impact_weights_infinity_norm_of_worst_substep_in_kilonewtons():
    f = torch.zeros(N, S, C, 3)
    # world 0: head (w=4) peaks at substep 2 with ‖f‖∞ = 500 N (Euclidean norm would be 616 N)
    f[0, :, 4] = torch.tensor([100.0, 100.0, 100.0])
    f[0, 2, 4] = torch.tensor([300.0, -500.0, 200.0])
    # elbows (w=2): 1 kN straight up at substep 0 only
    f[0, 0, 2, 2] = 1000.0
    # world 1: legs (w=1) at 3 kN along x in the last substep, 2 kN before
    f[1, :, 1, 0] = 2000.0
    f[1, 3, 1, 0] = -3000.0
    got = impact(make_ctx(make_state(contact_force=f)))
    want = torch.tensor([-((4 * 0.5) ** 2 + (2 * 1.0) ** 2), -((1 * 3.0) ** 2)])
    torch.testing.assert_close(got, want)


def test_impact_clips_each_component_and_honours_the_unit():
    f = torch.zeros(N, S, C, 3)
    f[0, 1, 0, 2] = 25_000.0  # pelvis, 25 kN: a solver spike
    f[1, 1, 4, 0] = 3_000.0  # head, 3 kN: below the clip
    state = make_state(contact_force=f)
    torch.testing.assert_close(impact(make_ctx(state)), torch.tensor([-(10.0**2), -((4 * 3.0) ** 2)]))
    torch.testing.assert_close(impact(make_ctx(state, force_clip=None)), torch.tensor([-(25.0**2), -((4 * 3.0) ** 2)]))
    # in newtons (force_unit 1) the same force is 10^6 times larger: the scale problem of issue 4
    torch.testing.assert_close(
        impact(make_ctx(state, force_unit=1.0, force_clip=None)), torch.tensor([-(25_000.0**2), -(12_000.0**2)])
    )


def test_root_acc_torques_joint_acc():
    state = make_state(
        root_lin_acc=torch.tensor([[1.0, 2.0, 2.0], [0.0, 0.0, -9.81]]),
        joint_torque=torch.tensor([[1.0, -2.0, 3.0], [0.0, 0.0, 0.0]]),
        joint_acc=torch.tensor([[10.0, 0.0, 0.0], [3.0, 4.0, 0.0]]),
    )
    ctx = make_ctx(state)
    torch.testing.assert_close(root_acc(ctx), torch.tensor([-9.0, -(9.81**2)]))
    torch.testing.assert_close(torques(ctx), torch.tensor([-14.0, 0.0]))
    torch.testing.assert_close(joint_acc(ctx), torch.tensor([-100.0, -25.0]))


def test_action_rate_and_acc_and_offset():
    ctx = make_ctx(
        action=torch.tensor([[1.0, 0.0, 0.0], [2.0, 2.0, 2.0]]),
        last_action=torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]),
        last_last_action=torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 0.0]]),
    )
    torch.testing.assert_close(action_rate(ctx), torch.tensor([-1.0, -3.0]))
    # a − 2a₁ + a₂: (1, 0, 1) and (0, 0, 0) — constant velocity costs nothing
    torch.testing.assert_close(action_acc(ctx), torch.tensor([-2.0, 0.0]))
    torch.testing.assert_close(offset(ctx), torch.ones(N))


def test_blend_endpoints_midpoint_and_monotone():
    t = torch.tensor([0.0, 1.0, 2.0, 3.0, -1.0])
    torch.testing.assert_close(blend(t, 2.0), torch.tensor([0.0, 0.5, 1.0, 1.0, 0.0]))
    ts = torch.linspace(0.0, 2.0, 201)
    u = blend(ts, 2.0)
    assert (u.diff() >= 0).all()
    # zero slope at both ends of the cubic spline
    assert u[1] < 1e-3 and 1.0 - u[-2] < 1e-3
    torch.testing.assert_close(blend(torch.tensor([0.5]), 2.0), torch.tensor([-2 * 0.25**3 + 3 * 0.25**2]))


def test_orientation_compares_tilt_only_and_is_blended():
    zero = torch.zeros(N)
    # target: pitched 90° (lying on the back or front); robot upright. R(θ̂)ᵀe_z = (−1, 0, 0) vs (0, 0, 1)
    pitched = quat_from_euler(zero, torch.full((N,), math.pi / 2), torch.tensor([0.0, 1.3]))  # heading irrelevant
    ctx = make_ctx(target_root_quat=pitched, blend=torch.tensor([1.0, 0.5]))
    torch.testing.assert_close(orientation(ctx), torch.tensor([-2.0, -1.0]))
    # a robot in the target tilt but another heading is on target
    robot = quat_from_euler(zero, torch.full((N,), math.pi / 2), torch.tensor([2.0, -0.7]))
    on_target = make_ctx(make_state(root_quat=robot), target_root_quat=pitched)
    torch.testing.assert_close(orientation(on_target), torch.zeros(N))


def test_joints_tracking_is_blended():
    state = make_state(joint_pos=torch.tensor([[0.1, 0.2, 0.3], [1.0, 0.0, 0.0]]))
    target = torch.tensor([[0.1, 0.0, 0.0], [0.0, 0.0, 0.0]])
    ctx = make_ctx(state, target_joint_pos=target, blend=torch.tensor([1.0, 0.0]))
    torch.testing.assert_close(joints(ctx), torch.tensor([-(0.04 + 0.09), 0.0]))


def test_sum_is_weighted_times_dt_and_logs_means():
    state = make_state(root_lin_acc=torch.tensor([[1.0, 2.0, 2.0], [0.0, 0.0, 0.0]]))
    cfg = RewardConfig(**{name: 0.0 for name in BUILTIN_TERMS} | {"root_acc": 0.2, "offset": 50.0})
    rewards = RewardSum(cfg, dt=0.02)
    assert rewards.names == ["root_acc", "offset"]
    r = rewards(make_ctx(state))
    torch.testing.assert_close(r, torch.tensor([0.02 * (0.2 * -9.0 + 50.0), 0.02 * 50.0]))
    rewards(make_ctx(make_state()))
    means = rewards.pop_means()
    assert means["offset"] == pytest.approx(1.0)
    assert means["root_acc"] == pytest.approx(0.02 * 0.2 * -9.0 / 2 / 2)
    assert rewards.pop_means() == {}


def test_impact_is_reported_per_component_when_the_components_are_named():
    """Given the components, the impact term's columns are its per-component summands (for a value head
    each, train.ppo.value_per_component); the reward and the logged per-term means are unchanged."""
    f = torch.zeros(N, S, C, 3)
    f[0, 2, 4, 1] = -500.0  # head (w=4), 0.5 kN
    f[0, 0, 2, 2] = 1000.0  # elbows (w=2), 1 kN
    f[1, 3, 1, 0] = 3000.0  # legs (w=1), 3 kN
    ctx = make_ctx(make_state(contact_force=f, root_lin_acc=torch.ones(N, 3)))
    cfg = RewardConfig(**{name: 0.0 for name in BUILTIN_TERMS} | {"impact": 200.0, "root_acc": 0.2})
    components = ["pelvis", "legs", "elbows", "shoulders", "head"]
    split, whole = RewardSum(cfg, dt=0.02, components=components), RewardSum(cfg, dt=0.02)
    assert split.columns == [f"impact/{c}" for c in components] + ["root_acc"] and whole.columns == whole.names
    columns = split.contributions(ctx)
    want = torch.zeros(N, C)
    want[0, 4], want[0, 2], want[1, 1] = -((4 * 0.5) ** 2), -((2 * 1.0) ** 2), -(3.0**2)
    torch.testing.assert_close(columns[:, :C], 0.02 * 200.0 * want)
    torch.testing.assert_close(columns.sum(1), whole(ctx))
    assert split.pop_means() == pytest.approx(whole.pop_means())


def test_weight_zero_skips_the_term():
    # contact_force None would crash the impact term: with weight 0 it is never called
    state = make_state()
    state.contact_force = None
    rewards = RewardSum(RewardConfig(impact=0.0), dt=0.02)
    assert "impact" not in rewards.names
    assert torch.isfinite(rewards(make_ctx(state))).all()


def test_table_i_defaults_and_flat_override_through_the_app_config():
    assert RewardConfig().weights() == {
        "impact": 200.0, "root_acc": 0.2, "orientation": 20.0, "joints": 1.0, "torques": 1e-3,
        "joint_acc": 7.5e-7, "action_rate": 0.1, "action_acc": 0.05, "offset": 50.0,
    }  # fmt: skip
    config = validate({"robot": {"name": "biped20"}, "reward": {"impact": 100}})
    assert config.reward.impact == 100.0
    with pytest.raises(ConfigError, match="'impcat' is neither a reward setting"):
        validate({"robot": {"name": "biped20"}, "reward": {"impcat": 100}})
    with pytest.raises(ConfigError, match="terms.impact: 'nosuch' is not a registered reward term"):
        validate({"robot": {"name": "biped20"}, "reward": {"terms": {"impact": "nosuch"}}})


@pytest.fixture
def plugin_term(tmp_path, monkeypatch):
    """A reward term registered by a real (tiny) installed distribution's entry point."""
    (tmp_path / "fallkit_test_term.py").write_text(
        textwrap.dedent(
            """
            import torch

            def soft_impact(ctx):
                return -ctx.state.contact_force.abs().amax(dim=(1, 3)).sum(dim=-1) / ctx.force_unit
            """
        )
    )
    info = tmp_path / "fallkit_test_term-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: fallkit-test-term\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text("[fallkit.rewards]\nsoft_impact = fallkit_test_term:soft_impact\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    registry.clear_cache()
    yield "soft_impact"
    monkeypatch.undo()
    registry.clear_cache()


def test_plugin_term_added_by_name_and_replacing_a_builtin(plugin_term):
    f = torch.zeros(N, S, C, 3)
    f[:, 0, 4, 2] = 2000.0  # 2 kN on the head
    ctx = make_ctx(make_state(contact_force=f))
    only = {name: 0.0 for name in BUILTIN_TERMS}
    added = RewardSum(RewardConfig(**only, **{plugin_term: 3.0}), dt=0.02)
    assert added.names == [plugin_term]
    torch.testing.assert_close(added(ctx), torch.full((N,), 0.02 * 3.0 * -2.0))
    # replace the built-in impact function, keeping the name and the weight 200
    replaced = RewardSum(RewardConfig(**(only | {"impact": 200.0}), terms={"impact": plugin_term}), dt=0.02)
    assert replaced.names == ["impact"]
    torch.testing.assert_close(replaced(ctx), torch.full((N,), 0.02 * 200.0 * -2.0))
    with pytest.raises(ValueError, match="a term weight must be a number"):
        RewardConfig(**{plugin_term: "heavy"})


def test_negative_weights_are_refused_with_the_fix():
    from fallkit.config import ConfigError, FallkitConfig, validate

    raw = FallkitConfig(robot={"name": "biped20"}).model_dump()
    raw["reward"]["impact"] = -200.0
    with pytest.raises(ConfigError, match=r"reward: impact=-200: weights must be >= 0 .* use 200"):
        validate(raw)
