"""A FallEnv's run state: what a checkpoint holds of the env to continue a training run exactly.

Not nn.Module's state_dict on purpose: this is the simulation's and the episodes' state, not parameters.
"""

from __future__ import annotations

from torchrl.envs import EnvBase

# the per-world episode buffers (fallkit.env.fall_env.FallEnv._make_episode_buffers)
_BUFFERS = ("step_count", "end_pose_ids", "goal_root_quat", "goal_joint_pos", "last_action", "last_last_action",
            "_motion", "sensitivity", "episode_steps")  # fmt: skip


def save_run_state(env: EnvBase) -> dict:
    """Everything needed to continue exactly: physics, episode buffers, disturbances, generators, replayed falls."""
    state = {name: getattr(env, name).clone() for name in _BUFFERS}
    state["sim"] = env.sim.state_dict()
    state["generators"] = (env._cpu_gen.get_state(), env._gen.get_state())
    state["initial_stock"] = env.initial_stock.state()  # drawn ahead, not yet used
    state["randomization"] = env.randomization.state()
    if env.disturbances is not None:
        d = env.disturbances
        state["disturbances"] = (d.active.clone(), d.remaining.clone(), d.wrench.clone())
    if env.level_replay is not None:
        state["level_replay"] = env.level_replay.state_dict()
    return state


def load_run_state(env: EnvBase, state: dict) -> None:
    """Restore what save_run_state returned (same robot, number of envs and config)."""
    if state["step_count"].shape != env.step_count.shape:
        raise ValueError(
            f"the saved run has {state['step_count'].shape[0]} envs, this one {env.num_envs} (sim.num_envs)"
        )
    for name in _BUFFERS:
        if name in ("sensitivity", "episode_steps") and name not in state:
            continue  # a run saved before these existed: the robot's weights and T, as built
        getattr(env, name).copy_(state[name])
    env.sim.load_state_dict(state["sim"])
    env._cpu_gen.set_state(state["generators"][0])
    env._gen.set_state(state["generators"][1])
    env.initial_stock.load(state.get("initial_stock"))  # a run saved before the stock: it starts empty
    if "randomization" in state:
        env.randomization.load(state["randomization"])
    if env.disturbances is not None and "disturbances" in state:
        d = env.disturbances
        d.active, d.remaining, d.wrench = (t.to(env.device) for t in state["disturbances"])
    if env.level_replay is not None and "level_replay" in state:  # else: the replay starts afresh
        env.level_replay.load_state_dict(state["level_replay"])
