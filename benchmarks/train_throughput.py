"""What the framework adds to the irreducible work of a PPO iteration (issue 6).

Measures, in one run, on the CPU backend:
  iteration   wall time of a real training iteration (collect num_envs x num_steps with
              the policy + PPO update + normaliser update), as fallkit.rl.trainer runs it
  simulation  the same number of env steps in pure simulation: MujocoSim.step with the
              nominal pose held, no policy, no env, no TensorDicts
  update      the same PPO update (same networks, epochs, minibatches) on random data of
              the same shapes
  ratio       iteration / (simulation + update)   — target <= 1.3

    python benchmarks/train_throughput.py [--envs 256] [--steps 24] [--hidden 256] [--iterations 3]
"""

from __future__ import annotations

import argparse
import json
import os
import time

import torch
from hydra import compose, initialize_config_module
from omegaconf import OmegaConf
from tensordict import TensorDict

from fallkit.app import register_configs
from fallkit.config import validate
from fallkit.env.build import make_env
from fallkit.rl.models import joint_prior, make_actor, make_critic
from fallkit.rl.ppo import PPO
from fallkit.rl.trainer import collect
from fallkit.robots import robot_spec
from fallkit.sim import make_sim


def config_for(args):
    register_configs()
    with initialize_config_module(config_module="fallkit.conf", version_base="1.3"):
        cfg = compose(
            config_name="config",
            overrides=[
                "train=quick",
                f"sim.num_envs={args.envs}",
                f"train.num_steps={args.steps}",
                f"train.actor_hidden=[{args.hidden},{args.hidden},{args.hidden}]",
                f"train.critic_hidden=[{args.hidden},{args.hidden},{args.hidden}]",
            ],
        )
    raw = OmegaConf.to_container(cfg, resolve=False)
    raw.pop("hydra", None)
    return validate(raw)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--envs", type=int, default=256)
    p.add_argument("--steps", type=int, default=24)
    p.add_argument("--hidden", type=int, default=256)
    p.add_argument("--iterations", type=int, default=3, help="timed iterations (after one warm-up)")
    args = p.parse_args()
    config = config_for(args)
    # as fallkit.rl.trainer: one torch thread while MuJoCo collects, all cores for the update
    update_threads = config.train.torch_threads or os.cpu_count() or 1
    torch.set_num_threads(1)
    spec = robot_spec(config.robot)
    tc = config.train

    # --- a real iteration ---------------------------------------------------------------
    env = make_env(config, spec, "train", seed=0)
    obs_dim = env.observation_spec["policy"].shape[-1]
    critic_dim = env.observation_spec["critic"].shape[-1]
    act_dim = env.action_spec.shape[-1]
    actor = make_actor(obs_dim, act_dim, tc.actor_hidden, tc.init_noise_std, joint_prior(config, spec))
    critic = make_critic(critic_dim, tc.critic_hidden)
    ppo = PPO(actor, critic, tc.ppo)
    td = env.reset()

    def iteration(td):
        batch, td = collect(env, actor, td, tc.num_steps)
        torch.set_num_threads(update_threads)
        ppo.update(batch)
        actor.module[0].module.norm.update(batch["policy"])
        critic.module.norm.update(batch["critic"])
        torch.set_num_threads(1)
        return td, batch

    td, batch = iteration(td)  # warm-up
    t = time.perf_counter()
    for _ in range(args.iterations):
        td, batch = iteration(td)
    t_iter = (time.perf_counter() - t) / args.iterations

    # --- pure simulation of the same env steps -------------------------------------------
    sim = make_sim(spec, args.envs, "mujoco", threads=config.sim.threads)
    from fallkit.env.samplers.initial_state import InitialStateSampler

    qpos, qvel = InitialStateSampler(spec).sample(args.envs, torch.Generator().manual_seed(0))
    sim.reset(torch.arange(args.envs), qpos, qvel)
    hold = torch.tensor(spec.nominal_q(), dtype=torch.float32).expand(args.envs, -1)
    t = time.perf_counter()
    for _ in range(args.iterations * tc.num_steps):
        sim.step(hold)
    t_sim = (time.perf_counter() - t) / args.iterations

    # --- the same update on random data ---------------------------------------------------
    shape = (args.envs, tc.num_steps)
    fake = TensorDict(
        {
            "policy": torch.randn(*shape, obs_dim),
            "critic": torch.randn(*shape, critic_dim),
            "action": torch.randn(*shape, act_dim),
            "loc": torch.randn(*shape, act_dim),
            "scale": torch.ones(*shape, act_dim),
            "action_log_prob": torch.randn(*shape),
            "next": {
                "critic": torch.randn(*shape, critic_dim),
                "reward": torch.randn(*shape, 1),
                "done": torch.zeros(*shape, 1, dtype=torch.bool),
                "terminated": torch.zeros(*shape, 1, dtype=torch.bool),
            },
        },
        batch_size=shape,
    )
    ppo2 = PPO(make_actor(obs_dim, act_dim, tc.actor_hidden, tc.init_noise_std), make_critic(critic_dim, tc.critic_hidden), tc.ppo)
    torch.set_num_threads(update_threads)
    ppo2.update(fake.clone())
    t = time.perf_counter()
    for _ in range(args.iterations):
        ppo2.update(fake.clone())
    t_update = (time.perf_counter() - t) / args.iterations
    torch.set_num_threads(1)

    ratio = t_iter / (t_sim + t_update)
    print(f"{args.envs} envs x {tc.num_steps} steps, actor/critic 3x{args.hidden}, {tc.ppo.epochs} epochs x {tc.ppo.num_minibatches} minibatches")
    print(f"  training iteration      {t_iter:7.3f} s")
    print(f"  pure simulation         {t_sim:7.3f} s")
    print(f"  PPO update, random data {t_update:7.3f} s")
    print(f"  ratio iteration / (simulation + update) = {ratio:.3f} (target <= 1.3)")
    print(json.dumps({
        "envs": args.envs, "steps": tc.num_steps, "hidden": args.hidden,
        "iteration_s": round(t_iter, 4), "simulation_s": round(t_sim, 4), "update_s": round(t_update, 4),
        "ratio": round(ratio, 4),
    }))  # fmt: skip


if __name__ == "__main__":
    main()
