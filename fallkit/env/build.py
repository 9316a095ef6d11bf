"""Build a run's FallEnv from its validated config (shared by training, evaluation and rendering)."""

from __future__ import annotations

from fallkit.config import FallkitConfig
from fallkit.env.fall_env import FallEnv
from fallkit.poses import EndPoseSet, load_end_poses
from fallkit.robots.spec import RobotSpec
from fallkit.sim import make_sim, sim_options


def make_env(
    config: FallkitConfig,
    spec: RobotSpec,
    split: str = "train",
    seed: int = 0,
    num_envs: int | None = None,
    poses: str | None = None,
    end_poses: EndPoseSet | None = None,
) -> FallEnv:
    """The FallEnv of `config`: its simulator backend, end poses of `split`, reward terms.

    `end_poses` given (e.g. eval.poses=auto's candidates restricted to one side) replaces the
    poses `poses` / `config.env.poses` names.
    """
    sim = make_sim(spec, num_envs or config.sim.num_envs, config.sim.backend, body_state=True, **sim_options(config.sim))
    if end_poses is None:
        end_poses = load_end_poses(poses or config.env.poses, spec, split=split, fraction=config.env.pose_fraction)
    return FallEnv(spec, config.env, config.reward, end_poses.to(sim.device), sim, seed=seed)
