"""The training episodes' end-pose draw: uniform (the paper) or, for a share, the pose the fall heads for."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from fallkit.config import EnvConfig, RewardConfig
from fallkit.env.fall_env import FallEnv
from fallkit.env.samplers.end_pose import EndPoseDraw
from fallkit.env.samplers.initial_state import InitialStateSampler
from fallkit.pose_choice import choose_by_heading, ground_directions, predicted_ground
from fallkit.poses.end_pose_set import random_end_poses
from fallkit.rotations import quat_rotate_inverse
from fallkit.sim import make_sim
from fallkit.sim.base import Layout


@pytest.fixture(scope="module")
def poses(biped):
    return random_end_poses(biped, 64, torch.Generator().manual_seed(0))


@pytest.fixture(scope="module")
def falls(biped):
    return InitialStateSampler(biped).sample(256, torch.Generator().manual_seed(3))


def base_frame_states(biped, qpos, qvel) -> tuple[np.ndarray, np.ndarray]:
    layout = Layout(biped)
    r, v = layout.root_qpos, layout.root_qvel
    quat = qpos[:, r + 3 : r + 7]
    return quat.numpy(), quat_rotate_inverse(quat, qvel[:, v : v + 3]).numpy()


def test_without_a_share_the_draw_is_the_papers_uniform_one_number_for_number(biped, poses, falls):
    draw = EndPoseDraw(poses.root_quat, Layout(biped))
    ids = draw(*falls, torch.Generator().manual_seed(5))
    assert torch.equal(ids, torch.randint(len(poses), (256,), generator=torch.Generator().manual_seed(5)))


def test_each_heading_choice_is_the_candidate_the_capture_point_picks(biped, poses, falls):
    """Of the poses drawn for a world, the one `fallkit.pose_choice.choose_by_heading` (eval.scorer=heading, the
    deployed controller's choice) picks; the rest keep their first draw."""
    k, share = 8, 0.5
    ids = EndPoseDraw(poses.root_quat, Layout(biped), share, k)(*falls, torch.Generator().manual_seed(5))
    g = torch.Generator().manual_seed(5)
    drawn, heading = torch.randint(len(poses), (256, k), generator=g), torch.rand(256, generator=g) < share
    quat, lin_vel = base_frame_states(biped, *falls)
    candidates = poses.root_quat.double().numpy()
    for i in range(256):
        best = drawn[i, choose_by_heading(quat[i : i + 1], lin_vel[i : i + 1], candidates[drawn[i].numpy()])[0]]
        assert ids[i] == (best if heading[i] else drawn[i, 0])
    assert 0.3 < heading.float().mean() < 0.7


def test_a_share_of_one_gives_falls_end_poses_lying_the_way_they_fall(biped, poses, falls):
    """Measured, not assumed: the angle between where each fall heads and its end pose's ground side is ~90°
    on average for a uniform draw and far smaller when every episode takes the closest of 8."""
    quat, lin_vel = base_frame_states(biped, *falls)
    heads = predicted_ground(quat, lin_vel)
    grounds = ground_directions(poses.root_quat.double().numpy())

    def mean_angle(share: float) -> float:
        ids = EndPoseDraw(poses.root_quat, Layout(biped), share, 8)(*falls, torch.Generator().manual_seed(5)).numpy()
        return math.degrees(np.arccos(np.clip(np.sum(heads * grounds[ids], axis=1), -1, 1)).mean())

    uniform, heading = mean_angle(0.0), mean_angle(1.0)
    assert 70 < uniform < 110 and heading < 0.6 * uniform


def test_the_env_draws_training_end_poses_with_the_configured_share(biped, poses):
    """env.heading_end_poses reaches the env's restarts; a reset to given falls (evaluation) keeps its poses."""
    cfg = EnvConfig(heading_end_poses=1.0, heading_candidates=4, noise={"scale": 0.0}, disturbances={"enabled": False})
    env = FallEnv(biped, cfg, RewardConfig(), poses, make_sim(biped, 4, "mujoco", body_state=True), seed=0)
    assert env.end_pose_draw.share == 1.0 and env.end_pose_draw.candidates == 4
    env.reset()
    assert ((env.end_pose_ids >= 0) & (env.end_pose_ids < len(poses))).all()
    qpos, qvel = InitialStateSampler(biped).sample(4, torch.Generator().manual_seed(1))
    given = torch.tensor([3, 1, 4, 1])
    env.reset_to(qpos, qvel, given)
    assert torch.equal(env.end_pose_ids.cpu(), given)
