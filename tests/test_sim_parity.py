"""The warp backend against the MuJoCo C backend: same states and setpoints, same physics.

Both backends build the same scene and run the same solver (Newton, pyramidal
cones, implicitfast); they differ in precision (mujoco_warp is float32, MuJoCo C
float64) and in summation order. Measured on Warp's CPU device over 0.5 s falls
(gains 0x..10x, pushes): root position <= 2e-6 m, joint angles <= 2e-4 rad,
velocities <= 5e-3, per-substep component forces <= 0.3 N at 1-4.5 kN peaks;
falls are chaotic, so differences grow after repeated impacts (about 2e-2 rad
and 60 N after 2 s). The tolerances below keep a 20x margin or more over those
figures (docs/gpu.md lists them), and a wrong sign, frame, substep or gain is
off by newtons to kilonewtons. The shared contract tests (tests/test_sim.py)
run on both backends through the `backend` fixture.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from fallkit.env.samplers.initial_state import InitialStateSampler
from fallkit.errors import ConfigError, SimBufferError
from fallkit.sim import make_sim

G = 9.81
STEPS = 25  # 0.5 s: the fall and its first impacts
SCALES = [1.0, 0.1, 10.0, 0.0, 1.0, 1.0]  # gain scales per world: policy, damping, freeze, zero torque
TOL = {  # max |warp - mujoco| over the whole fall
    "root_pos": 1e-4,  # m
    "root_quat": 1e-3,
    "joint_pos": 5e-3,  # rad
    "qvel": 0.1,  # m/s, rad/s
    "body_pos": 1e-4,  # m
    "body_vel": 0.1,
    "joint_torque": 0.5,  # N·m (actuators saturate at 4-33 N·m)
    "contact_force": 10.0,  # N, every component, every substep (peaks 1-2 kN)
    "impulse": 0.05,  # N·s per component over the fall (totals up to ~80 N·s)
}


def _fall(spec, backend: str, qpos, qvel, **options) -> dict[str, torch.Tensor]:
    n = len(qpos)
    sim = make_sim(spec, n, backend, body_state=True, **options)
    sim.reset(torch.arange(n), qpos, qvel)
    sim.set_gain_scale(torch.tensor(SCALES))
    pelvis = spec.mj_model().body(spec.root_body).id
    push = torch.zeros(n, 1, 6)
    push[4, 0] = torch.tensor([80.0, -40.0, 0.0, 0.0, 0.0, 5.0])  # force and torque, world frame
    push[5, 0, 1] = 120.0
    sim.set_external_wrench(torch.tensor([pelvis]), push)
    q0 = sim.state.joint_pos.clone()
    keys = ("root_pos", "root_quat", "joint_pos", "qvel", "body_pos", "body_vel", "joint_torque", "contact_force")
    rec: dict[str, list] = {k: [] for k in keys}
    for k in range(STEPS):
        st = sim.step(q0 + 0.1 * torch.sin(torch.arange(q0.shape[1]) + 0.3 * k))
        assert not st.unstable.any()
        for key in keys:
            rec[key].append(getattr(st, key).cpu().clone())
    out = {k: torch.stack(v, dim=1) for k, v in rec.items()}
    out["impulse"] = out["contact_force"].sum(dim=(1, 2)) * spec.timestep  # [N, C, 3]
    return out


@pytest.fixture(scope="session")
def falls(biped):
    """One short fall per world on both backends (the warp model compiles once per session)."""
    qpos, qvel = InitialStateSampler(biped).sample(len(SCALES), torch.Generator().manual_seed(0))
    return _fall(biped, "mujoco", qpos, qvel), _fall(biped, "warp", qpos, qvel, device="cpu")


@pytest.mark.parametrize("key", list(TOL))
def test_fall_agrees_with_mujoco(falls, key):
    ref, got = falls
    diff = (got[key] - ref[key]).abs().max().item()
    assert diff <= TOL[key], f"{key}: max |warp - mujoco| = {diff:.3g} > {TOL[key]}"


def test_the_fall_has_impacts(falls):
    """The comparison above is meaningful: robots hit the ground hard, on several components."""
    ref, _ = falls
    peak = ref["contact_force"].norm(dim=-1).amax(dim=(0, 1, 2))  # [C]
    assert peak.max() > 500.0 and (peak > 50.0).sum() >= 3


def test_lying_robot_rests_on_its_weight(biped):
    """Robots that fell and lie still: the components carry exactly the weight, on both backends."""
    n = 3
    qpos, qvel = InitialStateSampler(biped).sample(n, torch.Generator().manual_seed(3))
    weight = biped.mj_model().body_mass.sum() * G
    totals = {}
    for backend, options in (("warp", {"device": "cpu"}), ("mujoco", {})):
        sim = make_sim(biped, n, backend, **options)
        sim.reset(torch.arange(n), qpos, qvel)
        hold = sim.state.joint_pos.clone()
        for _ in range(100):  # 2 s: fall, then lie still
            state = sim.step(hold)
        assert state.qvel.abs().max() < 0.5
        f = state.contact_force  # [N, S, C, 3]
        totals[backend] = f[..., 2].sum(dim=-1).mean(dim=1)  # all components, mean over substeps
    torch.testing.assert_close(totals["warp"], torch.full((n,), weight, dtype=torch.float32), rtol=0.02, atol=0)
    torch.testing.assert_close(totals["warp"], totals["mujoco"], rtol=1e-2, atol=0)


def test_buffer_overflow_is_a_clear_error(biped):
    qpos, qvel = InitialStateSampler(biped).sample(2, torch.Generator().manual_seed(0))
    sim = make_sim(biped, 2, "warp", device="cpu", nconmax=1)
    sim.reset(torch.arange(2), qpos, qvel)
    with pytest.raises(SimBufferError, match=r"raise sim\.nconmax"):
        for _ in range(50):
            sim.step(sim.state.joint_pos)


def test_overflow_advice_names_the_setting():
    from mujoco_warp import OverflowType

    from fallkit.sim.warp_setup import overflow_advice as _overflow_advice

    assert "raise sim.njmax" in _overflow_advice(int(OverflowType.NEFC), 48, 212)
    assert "sim.njmax=212" in _overflow_advice(int(OverflowType.NEFC), 48, 212)
    text = _overflow_advice(int(OverflowType.NARROWPHASE | OverflowType.NEFC), 48, 212)
    assert "raise sim.nconmax" in text and "raise sim.njmax" in text


def test_default_buffers_cover_a_lying_robot(biped):
    from fallkit.sim.warp_setup import default_buffers

    nconmax, njmax = default_buffers(biped.mj_model())
    # 200 MuJoCo C falls of biped20 peaked at 14 contacts and 56 constraint rows per world
    assert nconmax >= 2 * 14 and njmax >= 4 * 56 - 20


def test_device_selection():
    from fallkit.sim.warp_setup import resolve_device

    assert resolve_device("cpu") == "cpu"
    if not torch.cuda.is_available():
        assert resolve_device("auto") == "cpu"
        with pytest.raises(ConfigError, match="sim.device: 'cuda:0' requested but no CUDA device"):
            resolve_device("cuda:0")
    with pytest.raises(ConfigError, match="sim.device: expected auto, cpu or cuda:N"):
        resolve_device("gpu")


def test_kernel_cache_location(monkeypatch, tmp_path):
    import warp as wp

    from fallkit.sim.warp_setup import init_warp, warp_cache_dir

    init_warp()  # Warp keeps one subfolder per Warp version
    assert Path(wp.config.kernel_cache_dir).is_relative_to(warp_cache_dir())
    monkeypatch.setenv("FALLKIT_WARP_CACHE", str(tmp_path / "kernels"))
    assert warp_cache_dir() == tmp_path / "kernels"
