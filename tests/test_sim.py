"""The BatchSim contract, on every backend in SIM_BACKENDS (conftest)."""

from __future__ import annotations

import copy

import mujoco
import numpy as np
import pytest
import torch

from fallkit.env.samplers.initial_state import InitialStateSampler
from fallkit.poses.checker import PoseChecker
from fallkit.sim import make_sim

G = 9.81


def standing_state(spec, n: int):
    """n copies of the nominal pose, soles just above the floor, at rest."""
    checker = PoseChecker(spec)
    lay = checker.layout
    q = lay.qpos(torch.zeros(n, 3, dtype=torch.float64), torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64).expand(n, 4),
                 torch.tensor(spec.nominal_q()).expand(n, -1))  # fmt: skip
    q, _ = checker.place_on_ground(q, 0.001)
    return q, torch.zeros(n, lay.nv, dtype=torch.float64)


def falling_states(spec, n: int, seed: int = 0):
    return InitialStateSampler(spec).sample(n, torch.Generator().manual_seed(seed))


def test_resting_contact_force_is_the_weight(biped, backend):
    sim = make_sim(biped, 2, backend)
    qpos, qvel = standing_state(biped, 2)
    sim.reset(torch.arange(2), qpos, qvel)
    hold = torch.tensor(biped.nominal_q(), dtype=torch.float32).expand(2, -1)
    for _ in range(75):  # 1.5 s to settle on the feet
        state = sim.step(hold)
    weight = biped.mj_model().body_mass.sum() * G
    legs = biped.component_names.index("legs")
    f = state.contact_force  # [N, S, C, 3]
    assert f[:, :, legs, 2].mean().item() == pytest.approx(weight, rel=0.02)
    others = [c for c in range(len(biped.components)) if c != legs]
    assert f[:, :, others].abs().max().item() < 1e-6  # only the feet touch anything
    assert not state.unstable.any()


def test_reset_subset_keeps_the_others(biped, backend):
    n = 4
    sim = make_sim(biped, n, backend)
    qpos, qvel = falling_states(biped, n)
    sim.reset(torch.arange(n), qpos, qvel)
    for _ in range(3):
        sim.step(sim.state.joint_pos.clone())
    before = sim.state.qpos.clone()
    new_q, new_v = falling_states(biped, 2, seed=1)
    sim.reset(torch.tensor([1, 3]), new_q, new_v)
    st = sim.state
    torch.testing.assert_close(st.qpos[[1, 3]], new_q.float(), atol=1e-6, rtol=0)
    torch.testing.assert_close(st.qvel[[1, 3]], new_v.float(), atol=1e-6, rtol=0)
    torch.testing.assert_close(st.qpos[[0, 2]], before[[0, 2]])
    lay = sim.layout
    torch.testing.assert_close(st.joint_pos[[1, 3]], new_q[:, lay.joint_qpos].float(), atol=1e-6, rtol=0)
    new_v[1, 0] = float("nan")  # a broken state is refused before any world changes
    with pytest.raises(ValueError, match=r"^sim.reset: qpos/qvel contain NaN or Inf$"):
        sim.reset(torch.tensor([1, 3]), new_q, new_v)
    torch.testing.assert_close(sim.state.qpos[[0, 2]], before[[0, 2]])


def test_gain_scaling_per_world(biped, backend):
    n = 3
    sim = make_sim(biped, n, backend)
    qpos, qvel = falling_states(biped, 1)
    sim.reset(torch.arange(n), qpos.expand(n, -1), qvel.expand(n, -1))
    sim.set_gain_scale(torch.tensor([0.0, 1.0, 10.0]))
    target = sim.state.joint_pos + 0.05
    state = sim.step(target)
    tau = state.joint_torque.abs().sum(dim=1)
    assert tau[0].item() == 0.0  # zero torque: actuators off
    assert tau[2].item() > tau[1].item() > 0.0
    # stiffer gains hold the setpoint: after a while, freeze tracks better than damping
    sim.set_gain_scale(torch.tensor([0.1, 1.0, 10.0]))
    for _ in range(10):
        state = sim.step(target)
    err = (state.joint_pos - target).abs().mean(dim=1)
    assert err[2] < err[0]


def test_instability_is_detected_reset_and_counted(biped, backend):
    n = 3
    sim = make_sim(biped, n, backend)
    qpos, qvel = falling_states(biped, n)
    sim.reset(torch.arange(n), qpos, qvel)
    pelvis = biped.mj_model().body("pelvis").id
    wrench = torch.zeros(n, 1, 6)
    wrench[1, 0, 0] = 1e9  # a force no robot survives: world 1 explodes
    sim.set_external_wrench(torch.tensor([pelvis]), wrench)
    state = sim.step(sim.state.joint_pos.clone())
    assert state.unstable.tolist() == [False, True, False]
    assert sim.num_unstable == 1
    # world 1 is back at its reset state, finite; the others went on
    torch.testing.assert_close(sim.state.qpos[1], qpos[1].float(), atol=1e-5, rtol=0)
    assert torch.isfinite(sim.state.qpos).all()
    sim.set_external_wrench(torch.tensor([pelvis]), torch.zeros(n, 1, 6))
    state = sim.step(sim.state.joint_pos.clone())
    assert not state.unstable.any() and sim.num_unstable == 1


def test_mujoco_batch_matches_single_world_mj_step(biped):
    """The batch simulator is MuJoCo: same states, setpoints and gains give the same trajectory."""
    n, steps = 3, 25
    sim = make_sim(biped, n, "mujoco")
    qpos, qvel = falling_states(biped, n)
    sim.reset(torch.arange(n), qpos, qvel)
    scales = [1.0, 0.1, 10.0]
    sim.set_gain_scale(torch.tensor(scales))
    targets = [sim.state.joint_pos.clone() + 0.1 * torch.sin(torch.arange(20.0) + k) for k in range(steps)]
    peak = torch.zeros(n, len(biped.components))
    for t in targets:
        st = sim.step(t)
        peak = torch.maximum(peak, st.contact_force.norm(dim=-1).amax(dim=1))

    base = biped.mj_model()
    for i, s in enumerate(scales):
        m = copy.copy(base)
        m.actuator_gainprm[:, 0] *= s
        m.actuator_biasprm[:, 1:3] *= s
        d = mujoco.MjData(m)
        d.qpos[:], d.qvel[:] = qpos[i].numpy(), qvel[i].numpy()
        d.ctrl[:] = qpos[i, sim.layout.joint_qpos].numpy()
        mujoco.mj_forward(m, d)
        ref_peak = np.zeros(len(biped.components))
        for t in targets:
            d.ctrl[:] = t[i].double().numpy()
            for _ in range(biped.substeps):
                mujoco.mj_step(m, d)
                f = -d.sensordata.reshape(-1, 3)  # per body, force received
                comp = sim.layout.component_sum.numpy() @ f
                ref_peak = np.maximum(ref_peak, np.linalg.norm(comp, axis=1))
        np.testing.assert_allclose(sim.state.qpos[i].numpy(), d.qpos, atol=1e-5)
        np.testing.assert_allclose(sim.state.qvel[i].numpy(), d.qvel, atol=1e-4, rtol=1e-5)
        # per-component peaks over every physics substep (float32 vs float64)
        np.testing.assert_allclose(peak[i].numpy(), ref_peak, rtol=1e-4, atol=1e-3)


def test_root_lin_acc_is_kinematic_gravity_not_subtracted(biped):
    """What the docstrings of SimState and the root_acc reward term say: Δv/Δt of the root, so a
    robot in free fall (2 m up, holding its pose) reads 9.81 m/s² downward, not 0."""
    sim = make_sim(biped, 1, "mujoco")
    qpos, qvel = standing_state(biped, 1)
    qpos[:, 2] += 2.0
    sim.reset(torch.arange(1), qpos, qvel)
    state = sim.step(torch.tensor(biped.nominal_q(), dtype=torch.float32)[None])
    assert state.root_lin_acc[0].tolist() == pytest.approx([0.0, 0.0, -G], abs=0.05)
