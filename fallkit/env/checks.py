"""What a FallEnv checks of its inputs before it builds anything: one line naming the mismatch."""

from __future__ import annotations

import torch

from fallkit.config import ConfigError, EnvConfig, RewardConfig
from fallkit.poses.end_pose_set import EndPoseSet
from fallkit.robots.spec import RobotSpec
from fallkit.sim.base import BatchSim


def check_inputs(
    spec: RobotSpec, env_cfg: EnvConfig, reward_cfg: RewardConfig, end_poses: EndPoseSet, sim: BatchSim
) -> None:
    """Raise on a simulator, end-pose set or blend time that does not fit the robot and episode."""
    if list(sim.spec.joint_names) != list(spec.joint_names):
        raise ValueError(f"FallEnv: the simulator's robot '{sim.spec.name}' has other joints than '{spec.name}'")
    if list(end_poses.joint_names) != list(spec.joint_names):
        raise ValueError(
            f"FallEnv: end poses are for joints {end_poses.joint_names[:3]}… of robot '{end_poses.robot}', "
            f"not the joints of robot '{spec.name}'"
        )
    if len(end_poses) == 0:
        raise ValueError("FallEnv: the end-pose set is empty")
    if sim.state.body_vel is None:
        raise ValueError(
            "FallEnv: the critic observes rigid-body velocities; make the simulator with body_state=True "
            "(fallkit.env.build.make_env does)"
        )
    if reward_cfg.blend_time > env_cfg.episode_length:
        raise ConfigError(
            f"reward.blend_time ({reward_cfg.blend_time} s) must not exceed env.episode_length "
            f"({env_cfg.episode_length} s): u(t) would never reach 1 (paper: T_blend <= T)"
        )


def check_reset_to(n: int, qpos: torch.Tensor, qvel: torch.Tensor, end_pose_ids: torch.Tensor, num_poses: int) -> None:
    """Raise unless `FallEnv.reset_to` got a state and an end pose in the set for each of its n worlds."""
    if qpos.shape[0] != n or qvel.shape[0] != n or end_pose_ids.shape != (n,):
        raise ValueError(
            f"reset_to: need {n} states and end-pose ids, got qpos {list(qpos.shape)}, "
            f"qvel {list(qvel.shape)}, end_pose_ids {list(end_pose_ids.shape)}"
        )
    if end_pose_ids.numel() and (int(end_pose_ids.min()) < 0 or int(end_pose_ids.max()) >= num_poses):
        raise ValueError(f"reset_to: end_pose_ids must be in [0, {num_poses})")
