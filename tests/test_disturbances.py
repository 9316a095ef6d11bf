"""Disturbance schedules and magnitudes (paper Table IV), vectorized over worlds."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fallkit import registry
from fallkit.config import DisturbanceConfig
from fallkit.env.samplers.disturbances import Disturbances

DT = 0.02


def runs(flags: np.ndarray) -> tuple[list[int], list[int]]:
    """Lengths (in steps) of the complete on and off runs of a boolean series, first and last run excluded."""
    change = np.flatnonzero(np.diff(flags.astype(np.int8))) + 1
    edges = np.concatenate(([0], change, [len(flags)]))
    on, off = [], []
    for a, b in zip(edges[1:-2], edges[2:-1]):
        (on if flags[a] else off).append(b - a)
    return on, off


@pytest.fixture(scope="module")
def history(biped):
    dist = registry.load("fallkit.samplers", "disturbances")(biped, 64, "cpu")
    g = torch.Generator().manual_seed(3)
    dist.reset(torch.ones(64, dtype=torch.bool), g)
    first_off = dist.remaining.clone()
    active, wrench = [], []
    for _ in range(2000):  # 40 s
        wrench.append(dist.step(DT, g).clone())
        active.append(dist.active.clone())
    return dist, first_off, torch.stack(active).numpy(), torch.stack(wrench).numpy()


def test_bodies_come_from_the_robot_spec(biped, history):
    dist = history[0]
    want = [b for role in ("hips", "feet", "elbows", "pelvis", "head") for b in biped.disturbance_bodies[role]]
    assert sorted(dist.body_names) == sorted(want)
    m = biped.mj_model()
    assert dist.body_ids.tolist() == [m.body(b).id for b in dist.body_names]


def test_on_and_off_durations_follow_table_iv(biped, history):
    dist, first_off, active, _ = history
    role = {b: r for r, bodies in biped.disturbance_bodies.items() for b in bodies}
    assert (first_off >= 0).all() and (first_off <= 3.0).all()
    for k, body in enumerate(dist.body_names):
        on_lo, on_hi = (2.0, 10.0) if role[body] in ("pelvis", "head") else (0.25, 2.0)
        on, off = [], []
        for w in range(active.shape[1]):
            a, b = runs(active[:, w, k])
            on += a
            off += b
        on, off = np.array(on) * DT, np.array(off) * DT
        assert len(on) > 20 and len(off) > 20, body
        # periods land on the policy-step grid: within one step of the drawn range
        assert on.min() >= on_lo - DT - 1e-6 and on.max() <= on_hi + DT + 1e-6, (body, on.min(), on.max())
        assert off.min() >= 1.0 - DT - 1e-6 and off.max() <= 3.0 + DT + 1e-6, (body, off.min(), off.max())
        # uniform draws: the mean sits mid-range
        assert abs(on.mean() - (on_lo + on_hi) / 2) < 0.15 * (on_hi - on_lo), body
        assert abs(off.mean() - 2.0) < 0.3, body


def test_wrench_is_constant_while_on_zero_while_off_and_within_magnitudes(history):
    _, _, active, wrench = history
    assert (wrench[~active] == 0).all()
    on = wrench[active]  # [k, 6]
    assert np.abs(on[:, :3]).max() <= 5.0 and np.abs(on[:, 3:]).max() <= 0.25
    # per axis uniform in [-max, max]: both signs, mean |value| ≈ max/2
    assert (on[:, :3] > 0).any() and (on[:, :3] < 0).any()
    assert abs(np.abs(on[:, :3]).mean() - 2.5) < 0.2 and abs(np.abs(on[:, 3:]).mean() - 0.125) < 0.01
    # constant within an on period, new draw at each new period
    same = active[1:] & active[:-1]
    assert (wrench[1:][same] == wrench[:-1][same]).all()
    starts = active[1:] & ~active[:-1]
    assert (wrench[1:][starts] != 0).all()


def test_reset_touches_only_masked_worlds(biped):
    dist = Disturbances(biped, DisturbanceConfig(), 8)
    g = torch.Generator().manual_seed(0)
    dist.reset(torch.ones(8, dtype=torch.bool), g)
    for _ in range(200):
        dist.step(DT, g)
    active, wrench, remaining = dist.active.clone(), dist.wrench.clone(), dist.remaining.clone()
    mask = torch.tensor([True, False] * 4)
    dist.reset(mask, g)
    assert not dist.active[mask].any() and (dist.wrench[mask] == 0).all()
    assert (dist.remaining[mask] <= 3.0).all()
    assert torch.equal(dist.active[~mask], active[~mask]) and torch.equal(dist.wrench[~mask], wrench[~mask])
    assert torch.equal(dist.remaining[~mask], remaining[~mask])


def test_seeded_and_configurable_roles(biped):
    def schedule(seed: int, cfg: DisturbanceConfig) -> torch.Tensor:
        d = Disturbances(biped, cfg, 4)
        g = torch.Generator().manual_seed(seed)
        d.reset(torch.ones(4, dtype=torch.bool), g)
        return torch.stack([d.step(DT, g).clone() for _ in range(100)])

    cfg = DisturbanceConfig()
    assert torch.equal(schedule(1, cfg), schedule(1, cfg))
    assert not torch.equal(schedule(1, cfg), schedule(2, cfg))
    # roles the config leaves out are not disturbed
    only_head = DisturbanceConfig(roles={"head": {"force": 1.0, "torque": 0.0, "on_time": (0.5, 0.5)}})
    d = Disturbances(biped, only_head, 4)
    assert d.body_names == biped.disturbance_bodies["head"]
    w = schedule(1, only_head)
    assert w[..., :3].abs().max() <= 1.0 and (w[..., 3:] == 0).all()
    with pytest.raises(ValueError, match="on_time: need 0 < min <= max"):
        DisturbanceConfig(roles={"head": {"on_time": (2.0, 1.0)}})
