"""Headless rendering: paired falls side by side, the end pose as a ghost, a video on disk."""

from __future__ import annotations

import os
import subprocess
import sys

import imageio.v3 as iio
import mujoco
import numpy as np
import pytest
import torch

from fallkit.config import ConfigError, FallkitConfig, RenderConfig
from fallkit.env.fall_env import FallEnv
from fallkit.eval import evaluate as ev
from fallkit.eval.render import FallPainter, frame_stride, render_rollout, write_video
from fallkit.eval.strategies import STRATEGIES
from fallkit.poses.checker import PoseChecker
from fallkit.poses.end_pose_set import random_end_poses
from fallkit.sim import make_sim

STEPS = 6


@pytest.fixture(scope="module")
def recorded(biped):
    cfg = ev.eval_run_config(FallkitConfig(robot={"name": biped.name}), STEPS * biped.policy_dt)
    poses = random_end_poses(biped, 3, torch.Generator().manual_seed(0))
    names = list(STRATEGIES)
    env = FallEnv(biped, cfg.env, cfg.reward, poses, make_sim(biped, len(names), body_state=True))
    trials = ev.draw_trials(env, 1, 5)
    return env, trials, ev.rollout(env, trials, names, record_states=True)


def test_headless_render_writes_videos_with_the_expected_frames(biped, recorded, tmp_path):
    env, trials, out = recorded
    rc = RenderConfig(width=160, height=112, fps=25, format="both")
    stride = frame_stride(biped.policy_hz, rc.fps)
    assert stride == 2
    with pytest.raises(ConfigError, match="render.fps"):
        frame_stride(biped.policy_hz, 60.0)
    frames = render_rollout(out, biped, env.end_poses, trials.pose_ids, rc)
    expected = STEPS // stride + 1  # the initial state, then every second policy step
    assert len(frames) == expected
    assert frames[0].shape == (112, 3 * 160, 3)  # three strategies side by side
    assert all(f.std() > 5.0 for f in frames)  # a scene, not a blank image
    paths = write_video(frames, tmp_path / "falls", biped.policy_hz / stride, rc.format)
    assert [p.suffix for p in paths] == [".mp4", ".gif"]
    assert all(p.stat().st_size > 1000 for p in paths)
    assert sum(1 for _ in iio.imiter(paths[0])) == expected
    assert iio.improps(paths[1]).n_images == expected


def test_ghost_and_contact_forces_are_drawn(biped, recorded):
    env, trials, out = recorded
    with FallPainter(biped, 160, 112) as painter:
        painter.look_at(np.array([0.0, 0.0, 0.3]), 120.0)
        q, v, tau = (x[-1, 0].numpy() for x in (out.qpos, out.qvel, out.joint_torque))
        painter.set_ghost(None)
        plain = painter.frame(q, v, tau).astype(int)
        ghost = q.copy()
        ghost[0] += 0.4  # beside the robot, so it cannot hide behind it
        painter.set_ghost(ghost)
        with_ghost = painter.frame(q, v, tau).astype(int)
        assert np.abs(with_ghost - plain).sum(axis=-1).astype(bool).mean() > 0.005

        # contact-force arrows: standing pressed 2 mm into the floor; switching them off changes the image
        lay = painter.layout
        nq = lay.qpos(torch.zeros(1, 3), torch.tensor([[1.0, 0, 0, 0]]), torch.as_tensor(biped.nominal_q()).float()[None])
        stand, _ = PoseChecker(biped).place_on_ground(nq.double(), clearance=-0.002)
        q, v, tau = stand[0].numpy(), np.zeros_like(v), np.zeros_like(tau)
        painter.set_ghost(None)
        arrows = painter.frame(q, v, tau).astype(int)
        assert painter.data.ncon > 0
        painter.option.flags[mujoco.mjtVisFlag.mjVIS_CONTACTFORCE] = False
        no_arrows = painter.frame(q, v, tau).astype(int)
        assert np.abs(no_arrows - arrows).sum(axis=-1).astype(bool).mean() > 0.001


def test_cli_render(tmp_path):
    """mode=render end to end, headless: a GIF of the three strategies side by side."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    args = ["mode=render", "eval.poses=artist", "eval.seconds=0.2", "render.fps=10", "render.format=gif",
            "render.width=160", "render.height=112", "hydra.run.dir=run"]  # fmt: skip
    r = subprocess.run([sys.executable, "-m", "fallkit", *args], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    props = iio.improps(tmp_path / "run" / "falls.gif")
    assert props.n_images == 10 // 5 + 1 and props.shape[1:3] == (112, 3 * 160)
