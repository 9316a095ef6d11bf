"""What a FallEnv checks of its inputs before it builds anything: one line naming the mismatch."""

from __future__ import annotations

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
