"""What the framework adds to the irreducible work of a PPO iteration (issues 6 and 15).

Measures, in one run, per world count, on either backend:
  iteration   wall time of a real training iteration, as fallkit.rl.trainer runs it, split
              into collection (num_envs x num_steps with the policy, from the trainer's staggered
              episode clocks, so worlds restart at every step as in training) and the PPO update
              (+ normaliser update)
  simulation  the same number of env steps in pure simulation: the backend's sim.step with
              the nominal pose held, no policy, no env, no TensorDicts
  update      the same PPO update (same networks, epochs, minibatches) on random observations
              and rewards of the same shapes, the actions drawn by the actor before each update
              (as collection draws them, so train.ppo.kl_stop stops the actor where training does)
and the ratios: iteration / (simulation + update) (CPU target <= 1.3), collection / simulation
(`collect_over_sim`, GPU target <= 1.4) and the update's share of an iteration (`update_share`,
GPU target <= 0.25), with env steps per second. On a GPU every phase ends on a device sync.

    python benchmarks/train_throughput.py [--envs 1024] [--steps 24] [--hidden 256] [--iterations 3] [--precision bfloat16]
    python benchmarks/train_throughput.py --backend warp --device cuda:0 --envs 4096 16384   # issue 15
"""

from __future__ import annotations

import argparse
import json
import os
import time

import torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type

from fallkit.app import composed_config
from fallkit.env.build import make_env
from fallkit.env.samplers.initial_state import InitialStateSampler
from fallkit.machine import subnormals_flushed
from fallkit.rl.models import joint_prior, make_actor, resolve_precision
from fallkit.rl.ppo import PPO
from fallkit.rl.trainer import collect
from fallkit.rl.value_heads import critic_for
from fallkit.robots import robot_spec
from fallkit.sim import make_sim, sim_options


def config_for(args, envs: int | None):
    """train=quick on the CPU backend; train=default (Table III networks) with sim=warp; envs None:
    the preset's own world count."""
    preset = ["train=quick"] if args.backend == "mujoco" else ["train=default", "sim=warp", f"sim.device={args.device}"]
    hidden = ",".join([str(args.hidden)] * 3)
    return composed_config(
        *preset, *([f"sim.num_envs={envs}"] if envs else []), f"train.num_steps={args.steps}",
        f"train.actor_hidden=[{hidden}]", f"train.critic_hidden=[{hidden}]", f"train.precision={args.precision}",
    )  # fmt: skip


def time_update(config, spec, rewards, dims: tuple[int, int, int], device, precision: str, iterations: int) -> float:
    """Seconds per PPO update (the config's networks, epochs and minibatches) on random observations and
    rewards of one iteration's shapes, the actions drawn by the actor itself before each update as collection
    draws them: what the update costs with no simulator in the way."""
    (obs_dim, critic_dim, act_dim), tc = dims, config.train
    sync = torch.cuda.synchronize if torch.device(device).type == "cuda" else (lambda: None)
    shape = (config.sim.num_envs, tc.num_steps)
    r = lambda *tail: torch.randn(*shape, *tail, device=device)  # noqa: E731
    fake = TensorDict(
        {
            "policy": r(obs_dim), "critic": r(critic_dim),  # the actor adds action, loc, scale, log-prob
            "next": {
                "critic": r(critic_dim), "reward": r(1), "reward_terms": r(len(rewards.columns)),
                "done": torch.zeros(*shape, 1, dtype=torch.bool, device=device),
                "terminated": torch.zeros(*shape, 1, dtype=torch.bool, device=device),
            },
        },
        batch_size=shape, device=device,
    )  # fmt: skip
    actor = make_actor(obs_dim, act_dim, tc.actor_hidden, tc.init_noise_std, precision=precision).to(device)
    critic = critic_for(config, spec, rewards, critic_dim, precision)[0].to(device)
    ppo = PPO(actor, critic, tc.ppo, rewards=rewards)
    torch.set_num_threads(config.train.torch_threads or os.cpu_count() or 1)

    def timed_update() -> float:
        # the batch as collection leaves it: drawn by the current policy, so the KL starts at 0 and the actor
        # steps as in training (a batch from an older policy would stop it at once under train.ppo.kl_stop)
        with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
            actor(fake)
        sync()
        start = time.perf_counter()
        ppo.update(fake.clone())
        sync()
        return time.perf_counter() - start

    with subnormals_flushed():  # as the trainer's update
        timed_update()
        t_update = sum(timed_update() for _ in range(iterations)) / iterations
    torch.set_num_threads(1)
    return t_update


def measure_update_only(args, envs: int) -> dict:
    """--update-only: the PPO update alone on args.device, in each precision asked. A MuJoCo C env of
    two worlds only gives the observation sizes and the reward layout: no Warp kernel is compiled."""
    cpu_args = argparse.Namespace(**{**vars(args), "backend": "mujoco"})
    config = config_for(cpu_args, envs)  # train=quick with args.hidden: the update's shapes
    spec = robot_spec(config.robot)
    env = make_env(config_for(cpu_args, 2), spec, "train", seed=0)
    dims = (env.observation_spec["policy"].shape[-1], env.observation_spec["critic"].shape[-1], env.action_spec.shape[-1])
    out = {"envs": envs, "device": args.device, "hidden": args.hidden}
    for name in args.update_precisions:
        tf32 = name == "tf32"  # float32 storage, TensorFloat-32 matrix products (CUDA only)
        if torch.device(args.device).type == "cuda":
            torch.backends.cuda.matmul.allow_tf32 = torch.backends.cudnn.allow_tf32 = tf32
        precision = "float32" if tf32 else resolve_precision(name, args.device)
        out[name] = round(time_update(config, spec, env.rewards, dims, args.device, precision, args.iterations), 4)
        print(f"{envs} envs x {config.train.num_steps} steps, 3x{args.hidden}: PPO update on {args.device} in {name} "
              f"({precision}{' + TF32' if tf32 else ''}): {out[name]:.3f} s")  # fmt: skip
    return out


def measure(args, envs: int) -> dict:
    """The three timings and their ratios for one world count."""
    config = config_for(args, envs)
    gpu = config.sim.backend == "warp" and args.device.startswith("cuda")
    sync = torch.cuda.synchronize if gpu else (lambda: None)
    # as fallkit.rl.trainer: one torch thread while MuJoCo collects, all cores for the update
    update_threads = config.train.torch_threads or os.cpu_count() or 1
    torch.set_num_threads(1)
    spec = robot_spec(config.robot)
    tc = config.train

    # --- a real iteration ---------------------------------------------------------------
    env = make_env(config, spec, "train", seed=0)
    device = env.device
    precision = resolve_precision(tc.precision, device)  # as fallkit.rl.trainer resolves it
    obs_dim = env.observation_spec["policy"].shape[-1]
    critic_dim = env.observation_spec["critic"].shape[-1]
    act_dim = env.action_spec.shape[-1]
    prior = joint_prior(config, spec)
    actor = make_actor(obs_dim, act_dim, tc.actor_hidden, tc.init_noise_std, prior, precision=precision).to(device)
    critic = critic_for(config, spec, env.rewards, critic_dim, precision)[0].to(device)  # as the trainer builds it
    ppo = PPO(actor, critic, tc.ppo, rewards=env.rewards)
    td = env.reset()
    env.stagger_episodes()  # as the trainer starts: episodes end and restart at every step, as in training

    def iteration(td):
        sync()
        t0 = time.perf_counter()
        batch, td = collect(env, actor, td, tc.num_steps)
        sync()
        t1 = time.perf_counter()
        torch.set_num_threads(update_threads)
        with subnormals_flushed():
            ppo.update(batch)
        actor.module[0].module.norm.update(batch["policy"])
        critic.module.norm.update(batch["critic"])
        torch.set_num_threads(1)
        sync()
        return td, t1 - t0, time.perf_counter() - t1

    td, _, _ = iteration(td)  # warm-up
    collect_s = update_s = 0.0
    for _ in range(args.iterations):
        td, c, u = iteration(td)
        collect_s, update_s = collect_s + c / args.iterations, update_s + u / args.iterations
    t_iter = collect_s + update_s

    # --- pure simulation of the same env steps -------------------------------------------
    sim = make_sim(spec, envs, config.sim.backend, body_state=True, **sim_options(config.sim))
    qpos, qvel = InitialStateSampler(spec).sample(envs, torch.Generator().manual_seed(0))
    sim.reset(torch.arange(envs), qpos, qvel)
    hold = torch.tensor(spec.nominal_q(), dtype=torch.float32, device=sim.device).expand(envs, -1)
    sim.step(hold)
    sync()
    t = time.perf_counter()
    for _ in range(args.iterations * tc.num_steps):
        sim.step(hold)
    sync()
    t_sim = (time.perf_counter() - t) / args.iterations

    t_update = time_update(config, spec, env.rewards, (obs_dim, critic_dim, act_dim), device, precision, args.iterations)

    steps = envs * tc.num_steps
    out = {
        "envs": envs, "iteration_s": round(t_iter, 4), "collect_s": round(collect_s, 4),
        "update_in_iteration_s": round(update_s, 4), "simulation_s": round(t_sim, 4), "update_s": round(t_update, 4),
        "ratio": round(t_iter / (t_sim + t_update), 4), "collect_over_sim": round(collect_s / t_sim, 4),
        "update_share": round(update_s / t_iter, 4), "env_steps_per_s": round(steps / t_iter),
        "sim_env_steps_per_s": round(steps / t_sim), "precision": precision,
    }  # fmt: skip
    print(f"{envs} envs x {tc.num_steps} steps on {config.sim.backend} ({device}), actor/critic 3x{args.hidden}, "
          f"{tc.ppo.epochs} epochs x {tc.ppo.num_minibatches} minibatches, {precision}")  # fmt: skip
    print(f"  training iteration      {t_iter:7.3f} s  (collection {collect_s:.3f} s + update {update_s:.3f} s)")
    print(f"  pure simulation         {t_sim:7.3f} s")
    print(f"  PPO update, random data {t_update:7.3f} s")
    print(f"  iteration / (simulation + update) = {out['ratio']:.3f} (CPU target <= 1.3); collection / simulation "
          f"= {out['collect_over_sim']:.2f} (GPU target <= 1.4); update share {out['update_share']:.2f} "
          f"(GPU target <= 0.25); {out['env_steps_per_s']} env steps/s")  # fmt: skip
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--backend", choices=("mujoco", "warp"), default="mujoco")
    p.add_argument("--device", default="cuda:0", help="warp device (cuda:N, or cpu to try it here)")
    p.add_argument("--envs", type=int, nargs="+", default=None, help="world counts (default: train=quick's; warp 4096 16384)")
    p.add_argument("--steps", type=int, default=24)
    p.add_argument("--hidden", type=int, default=None, help="width of the 3 layers (default: 256; warp 512)")
    p.add_argument("--iterations", type=int, default=3, help="timed iterations (after one warm-up)")
    p.add_argument("--precision", choices=("auto", "float32", "bfloat16"), default="auto", help="train.precision")
    p.add_argument("--update-only", nargs="+", dest="update_precisions", metavar="PRECISION", default=None,
                   choices=("auto", "float32", "bfloat16", "tf32"),
                   help="time only the PPO update on --device, in each precision (tf32: float32 with TensorFloat-32 "
                        "products, CUDA only); builds no simulator, so compiles no Warp kernel")  # fmt: skip
    args = p.parse_args()
    warp = args.backend == "warp"
    args.hidden = args.hidden or (512 if warp else 256)
    args.envs = args.envs or ([4096, 16384] if warp else [config_for(args, None).sim.num_envs])  # train=quick's
    if args.update_precisions:
        if "tf32" in args.update_precisions and not args.device.startswith("cuda"):
            p.error("--update-only tf32 needs a CUDA --device (TensorFloat-32 is an NVIDIA GPU format)")
        print(json.dumps({"update_only": [measure_update_only(args, n) for n in args.envs]}))
        return
    runs = [measure(args, n) for n in args.envs]
    summary = {
        "backend": args.backend, "device": args.device if warp else "cpu", "steps": args.steps,
        "hidden": args.hidden, "precision": runs[0]["precision"], "runs": runs,  # as resolved: auto says which
        **{k: {str(r["envs"]): r[k] for r in runs} for k in ("collect_over_sim", "update_share", "env_steps_per_s")},
    }  # fmt: skip
    if len(runs) == 1:  # the single-count form of issue 6 keeps its flat keys
        summary.update({k: runs[0][k] for k in ("envs", "iteration_s", "simulation_s", "update_s", "ratio")})
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
