"""The same code trains a quadruped: go1 from the plugin under plugins/ (issue 8)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from fallkit.poses import load_end_poses
from fallkit.rl.checkpoint import load_checkpoint

pytest.importorskip("fallkit_go1", reason="install plugins/fallkit-go1 (scripts/setup.sh does)")


@pytest.mark.slow
def test_go1_end_poses_then_training(tmp_path):
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}

    def fallkit(*args: str) -> subprocess.CompletedProcess:
        r = subprocess.run([sys.executable, "-m", "fallkit", *args], cwd=tmp_path, env=env, capture_output=True,
                           text=True, timeout=600)  # fmt: skip
        assert r.returncode == 0, (r.stdout + r.stderr)[-3000:]
        return r

    # the end-pose generator runs on the quadruped unchanged
    fallkit("mode=poses", "robot=go1", "dataset.train=48", "dataset.test=16", "dataset.num_worlds=64",
            "dataset.out=go1_poses.npz", "dataset.artist=null", "dataset.sheet=8", "hydra.run.dir=poses")  # fmt: skip
    from fallkit.api import get_robot

    spec = get_robot("go1")
    assert len(load_end_poses(tmp_path / "go1_poses.npz", spec, split="train")) == 48
    # and the same training code trains it
    fallkit("robot=go1", "train=quick", "sim.num_envs=8", "train.num_steps=4", "train.iterations=2",
            "train.actor_hidden=[16,16]", "train.critic_hidden=[16,16]", "train.evaluate=false",
            f"env.poses={tmp_path / 'go1_poses.npz'}", "hydra.run.dir=train")  # fmt: skip
    ckpt = load_checkpoint(tmp_path / "train")
    assert ckpt["robot"] == "go1" and ckpt["iteration"] == 2
