"""The physics-informed end-pose generator (paper Sec. IV-C), on the real simulator."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest
import torch

from fallkit.config import DatasetConfig, SettleConfig
from fallkit.poses.bins import OrientationBins, select_uniform, uniformity
from fallkit.poses.checker import PoseChecker
from fallkit.poses.generator import EndPoseGenerator, _Candidates, sample_root_quat
from fallkit.poses.settle import settle
from fallkit.rotations import gravity_in_frame, quat_rotate
from fallkit.sim.base import Layout

# A small run that still has to rebalance: 8 coarse bins, so it converges in a few hundred drops.
SMALL = dict(train=120, test=12, num_worlds=96, bands=2, sectors=4, tolerance=0.15, seed=3)


@pytest.fixture(scope="module")
def small_run(biped):
    return EndPoseGenerator(biped, DatasetConfig(**SMALL)).run(progress=False)


def _tilt_deg(a: torch.Tensor, b: torch.Tensor) -> np.ndarray:
    ga, gb = gravity_in_frame(a.double()), gravity_in_frame(b.double())
    return np.degrees(np.arccos((ga * gb).sum(-1).clamp(-1, 1).numpy()))


def test_root_orientation_is_pitch_then_yaw_about_the_robots_own_axis():
    g = torch.Generator().manual_seed(7)
    q = sample_root_quat(4000, g)
    g = torch.Generator().manual_seed(7)  # the same draws, in the sampler's order
    pitch = (2 * torch.rand(4000, generator=g, dtype=torch.float64) - 1) * math.pi
    yaw = (2 * torch.rand(4000, generator=g, dtype=torch.float64) - 1) * math.pi
    e = torch.eye(3, dtype=torch.float64)
    # R = Ry(pitch) Rz(yaw): the long (z) axis only feels the pitch, the yaw turns the body about it
    z_axis = quat_rotate(q, e[2].expand(4000, 3))
    expected_z = torch.stack((torch.sin(pitch), torch.zeros_like(pitch), torch.cos(pitch)), -1)
    assert torch.allclose(z_axis, expected_z, atol=1e-9)
    x_axis = quat_rotate(q, e[0].expand(4000, 3))
    expected_x = torch.stack(
        (torch.cos(pitch) * torch.cos(yaw), torch.sin(yaw), -torch.sin(pitch) * torch.cos(yaw)), -1
    )
    assert torch.allclose(x_axis, expected_x, atol=1e-9)
    # both angles cover the full ±180°
    assert pitch.min() < -3.1 and pitch.max() > 3.1 and yaw.min() < -3.1 and yaw.max() > 3.1


def test_drop_candidates_are_within_limits_collision_free_and_0_04_m_up(biped):
    checker = PoseChecker(biped)
    qpos, joints = _Candidates(checker, torch.Generator().manual_seed(0), 0.04, block=256).take(300)
    lim = torch.as_tensor(biped.joint_limits)
    assert ((joints >= lim[:, 0]) & (joints <= lim[:, 1])).all()
    colliding, lowest = checker.check(qpos)
    assert not colliding.any()
    assert torch.allclose(qpos[:, 2] + lowest, torch.full((300,), 0.04, dtype=torch.float64), atol=1e-9)
    # the rejection has work to do: about 10 % of uniform draws self-collide for biped20
    lay = checker.layout
    raw = lim[:, 0] + (lim[:, 1] - lim[:, 0]) * torch.rand(400, len(lim), generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    up = lay.qpos(torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64).expand(400, 3), qpos[:1, 3:7].expand(400, 4), raw)
    assert checker.check(up)[0].float().mean() > 0.03


def test_a_settled_pose_stays_put_with_frozen_gains(biped):
    lay = Layout(biped)
    checker = PoseChecker(biped)
    qpos, joints = _Candidates(checker, torch.Generator().manual_seed(11), 0.04, block=96).take(96)
    cfg = SettleConfig()
    res = settle(biped, qpos, cfg)
    assert res.settled.float().mean() > 0.8
    q, hold = res.qpos[res.settled], joints[res.settled]
    assert (res.seconds[res.settled] <= cfg.max_time + 1e-6).all()
    from fallkit.sim import make_sim

    n = len(q)
    sim = make_sim(biped, n)
    sim.set_gain_scale(torch.full((n,), cfg.gain_scale))
    sim.reset(torch.arange(n), q, torch.zeros(n, lay.nv, dtype=torch.float64))
    for _ in range(50):  # one more second, same frozen setpoint
        st = sim.step(hold.float())
    tilt = _tilt_deg(q[:, 3:7], st.root_quat)
    moved = (st.joint_pos.double() - q[:, lay.joint_qpos]).abs().amax(1).numpy()
    slid = (st.root_pos[:, :2].double() - q[:, :2]).norm(dim=1).numpy()
    # rest detection can be fooled by a pose balanced on a tipping point; nearly all must hold still
    assert np.median(tilt) < 0.3 and np.mean(tilt < 1.0) >= 0.9, np.quantile(tilt, [0.5, 0.9, 1.0])
    assert np.median(moved) < 0.01 and np.mean(moved < 0.05) >= 0.9
    assert np.median(slid) < 0.005


def test_orientations_sampled_in_a_bin_land_in_it():
    bins = OrientationBins(6, 8)
    wanted = torch.arange(48).repeat(20)
    quat = bins.sample(wanted, torch.Generator().manual_seed(0))
    assert torch.equal(bins.index(quat), wanted) and torch.allclose(quat.norm(dim=-1), torch.ones(len(quat), dtype=quat.dtype))


def test_targeted_drops_fill_the_same_bins_and_report_side_shares(biped):
    """dataset.targeted aims a share of the drops at covered bins short of poses; the natural
    frequencies (rarity) come from the uniform drops only."""
    from fallkit.poses.bins import side_shares

    cfg = DatasetConfig(**{**SMALL, "targeted": 0.5, "min_share": 0.5})
    gen = EndPoseGenerator(biped, cfg).run(progress=False)
    assert len(gen.joint_pos) == SMALL["train"] + SMALL["test"] and gen.stats["uniform_within_tolerance"]
    shares = side_shares(gen.root_quat)
    assert set(shares) == {"front", "back", "left", "right", "bottom", "top"} and abs(sum(shares.values()) - 1) < 1e-9


def test_equal_area_bins_split_the_sphere_evenly():
    bins = OrientationBins(6, 8)
    d = torch.randn(200_000, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    d = d / d.norm(dim=1, keepdim=True)
    # a quaternion whose ground direction -R^T e_z is d: rotate e_z onto -d
    up = -d
    axis = torch.cross(torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand_as(up), up, dim=1)
    angle = torch.acos(up[:, 2].clamp(-1, 1))
    axis = axis / axis.norm(dim=1, keepdim=True).clamp(min=1e-12)
    q_inv = torch.cat((torch.cos(angle / 2)[:, None], torch.sin(angle / 2)[:, None] * axis), 1)  # R^T e_z = up
    q = q_inv * torch.tensor([1.0, -1.0, -1.0, -1.0], dtype=torch.float64)
    assert torch.allclose(bins.down(q), d, atol=1e-9)
    counts = torch.bincount(bins.index(q), minlength=bins.count).double()
    assert (counts.max() / counts.min()) < 1.08  # equal areas (sampling noise ~2 %)
    # sector 0 is lying on the front (ground direction +x), sector 2 on the left side (+y)
    front = bins.index(torch.tensor([[0.7071, 0.0, 0.7071, 0.0]], dtype=torch.float64))  # pitch +90°
    assert int(front) % 8 == 0
    left = bins.index(torch.tensor([[0.7071, -0.7071, 0.0, 0.0]], dtype=torch.float64))  # roll -90°: left side down
    assert int(left) % 8 == 2


def test_water_filling_keeps_rare_bins_and_levels_the_rest():
    counts = np.array([500, 40, 300, 3, 120, 90])
    keep, rare, ok = select_uniform(counts, counts, total=400, min_share=0.5)
    assert ok and keep.sum() == 400
    assert list(rare) == [False, True, False, True, False, False]  # below half of a uniform share (88)
    assert keep[1] == 40 and keep[3] == 3  # rare bins keep all they have
    cov = keep[~rare]
    assert cov.max() - cov.min() <= 1 and (keep <= counts).all()
    assert uniformity(keep, rare) > 0.98
    # the under-filled bin stays below the level: uniformity drops, the caller keeps sampling
    keep, rare, ok = select_uniform(np.array([500, 60, 300, 200]), np.array([500, 60, 300, 200]), 600, 0.1)
    assert ok and keep[1] == 60 and uniformity(keep, rare) < 0.5
    # not enough settled poses at all
    assert not select_uniform(np.array([5, 5]), np.array([5, 5]), 100, 0.5)[2]


def test_small_run_is_rebalanced_uniform_within_tolerance(small_run, biped):
    st = small_run.stats
    total = SMALL["train"] + SMALL["test"]
    assert len(small_run.joint_pos) == total == st["kept"] == sum(st["hist_after"])
    assert st["uniform_within_tolerance"] and st["uniformity"] >= 1 - SMALL["tolerance"]
    after, before = np.array(st["hist_after"]), np.array(st["hist_before"])
    rare = np.zeros(len(after), bool)
    rare[st["rare_bins"]] = True
    covered = after[~rare]
    assert covered.min() >= (1 - SMALL["tolerance"]) * covered.max()
    # rebalancing did discard: the most popular bin was thinned to the common level
    assert before.max() > 1.5 * after.max()
    assert st["drops"] > total and st["aborted_overfull"] + st["discarded_overfull"] > 0
    # the recorded bins are the bins of the recorded orientations
    bins = OrientationBins(SMALL["bands"], SMALL["sectors"])
    assert torch.equal(bins.index(small_run.root_quat), small_run.bin)
    assert np.bincount(small_run.bin.numpy(), minlength=bins.count).tolist() == st["hist_after"]
    # splits: sizes, and each bin's test share follows its size
    assert (small_run.split == "test").sum() == SMALL["test"]
    # settled poses are within the limits and lie on the floor
    lim = torch.as_tensor(biped.joint_limits)
    assert ((small_run.joint_pos >= lim[:, 0]) & (small_run.joint_pos <= lim[:, 1])).all()
    assert (small_run.root_height > 0).all() and (small_run.root_height < 0.5).all()


def test_same_seed_same_dataset_other_seed_other_dataset(small_run, biped):
    # one thread instead of all: each world is stepped by one thread, so the result is the same
    again = EndPoseGenerator(biped, DatasetConfig(**SMALL), threads=1).run(progress=False)
    assert torch.equal(again.joint_pos, small_run.joint_pos)
    assert torch.equal(again.root_quat, small_run.root_quat)
    assert (again.split == small_run.split).all()
    other = EndPoseGenerator(biped, DatasetConfig(**{**SMALL, "seed": 4, "train": 30, "test": 0})).run(progress=False)
    assert not torch.equal(other.joint_pos[:30], small_run.joint_pos[:30])


@pytest.mark.slow
def test_mode_poses_writes_dataset_sheets_and_histogram(tmp_path, biped):
    out = tmp_path / "p.npz"
    cmd = [
        sys.executable, "-m", "fallkit", "mode=poses", "robot=biped20", "dataset.train=40", "dataset.test=4",
        "dataset.num_worlds=48", "dataset.bands=2", "dataset.sectors=4", "dataset.sheet=4", f"dataset.out={out}",
        f"hydra.run.dir={tmp_path / 'run'}",
    ]  # fmt: skip
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "after rebalancing" in r.stdout
    for name in ("orientation_bins.png", "poses_generated.png", "poses_artist.png"):
        assert (tmp_path / "run" / name).stat().st_size > 10_000, name
    stats = json.loads((tmp_path / "run" / "poses_stats.json").read_text())
    assert sum(stats["hist_after"]) == 44 and stats["drops"] >= 44
    from PIL import Image

    sheet = np.asarray(Image.open(tmp_path / "run" / "poses_artist.png"))
    assert sheet.shape[0] > 300 and sheet.std() > 10  # ten rendered poses, not a blank image
    from fallkit.poses import load_end_poses

    assert len(load_end_poses(out, biped, "train")) == 40 and len(load_end_poses(out, biped, "test")) == 4
    bad = subprocess.run([*cmd[:3], "mode=poses", "dataset.train=0"], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "dataset.train" in bad.stderr
