"""Build a run's objects from its validated config (shared by train, eval and render)."""

from __future__ import annotations

from fallkit.config import FallkitConfig
from fallkit.robots.spec import RobotSpec
from fallkit.sim import make_sim


def make_env(
    config: FallkitConfig,
    spec: RobotSpec,
    split: str = "train",
    seed: int = 0,
    num_envs: int | None = None,
    poses: str | None = None,
):
    """The FallEnv of `config`: its simulator backend, end poses of `split`, reward terms."""
    from fallkit.env import FallEnv
    from fallkit.pose_files import load_end_poses

    sim_cfg = config.sim
    options: dict = {"max_speed": sim_cfg.max_speed, "body_state": True}
    if sim_cfg.backend == "mujoco":
        options["threads"] = sim_cfg.threads
    else:
        options.update(device=sim_cfg.device, nconmax=sim_cfg.nconmax, njmax=sim_cfg.njmax)
    sim = make_sim(spec, num_envs or sim_cfg.num_envs, sim_cfg.backend, **options)
    end_poses = load_end_poses(poses or config.env.poses, spec, split=split, fraction=config.env.pose_fraction)
    return FallEnv(spec, config.env, config.reward, end_poses.to(sim.device), sim, seed=seed)
