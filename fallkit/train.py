"""`mode=train`: PPO on the batched falling environment (paper Sec. V-A, Table III).

One iteration, read top to bottom:
  collect   num_steps policy steps in every env (TorchRL's step_and_maybe_reset:
            finished envs restart with a fresh initial state and end pose)
  learn     PPO.update: GAE, epochs x minibatches of ClipPPOLoss, adaptive lr
  normalise merge the batch into the running observation statistics (after the
            update, so the update saw the statistics the data was collected with)
  log       progress bar, TensorBoard scalars, metrics.csv
  save      checkpoints/iter_<k>.pt every checkpoint_every iterations and last.pt at
            the end, atomically; SIGINT/SIGTERM finish the iteration, save, and stop.

Under torchrun each rank steps its own envs with its own seed; gradients, KL and
observation statistics are averaged over ranks; rank 0 logs and saves.
"""

from __future__ import annotations

import csv
import logging
import os
import signal
import time
from pathlib import Path

import torch
import torch.distributed as dist
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type
from tqdm import tqdm

from fallkit.build import make_env
from fallkit.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from fallkit.config import ConfigError, FallkitConfig
from fallkit.models import HoldPrior, make_actor, make_critic, policy_net, value_net
from fallkit.observations import actor_layout
from fallkit.ppo import PPO, distributed

log = logging.getLogger(__name__)


def run_train(config: FallkitConfig, run_dir: Path) -> Path:
    tc = config.train
    rank = _init_distributed(config)
    # MuJoCo's threads own the cores while collecting; the update has them to itself
    collect_threads, update_threads = 1, tc.torch_threads or os.cpu_count() or 1
    torch.set_num_threads(collect_threads)
    seed = config.seed + 1_000_003 * rank
    torch.manual_seed(seed)
    spec = config.robot.spec()
    env = make_env(config, spec, split="train", seed=seed)
    obs_dim = env.observation_spec["policy"].shape[-1]
    critic_dim = env.observation_spec["critic"].shape[-1]
    act_dim = env.action_spec.shape[-1]
    actor = make_actor(obs_dim, act_dim, tc.actor_hidden, tc.init_noise_std, hold_prior(config, spec)).to(env.device)
    critic = make_critic(critic_dim, tc.critic_hidden).to(env.device)
    if distributed():  # every rank starts from rank 0's weights (as DistributedDataParallel does)
        for tensor in [*actor.state_dict().values(), *critic.state_dict().values()]:
            dist.broadcast(tensor, src=0)
    ppo = PPO(actor, critic, tc.ppo)
    shuffle = torch.Generator().manual_seed(seed)

    start, td = 0, None
    if config.resume:
        start, td = _resume(config, spec, env, actor, critic, ppo, shuffle)
    ckpt_dir = run_dir / "checkpoints"
    main_rank = rank == 0
    logger = _Logger(run_dir, enabled=main_rank)
    stop = _StopFlag()
    started = time.monotonic()
    episode_impact = torch.zeros(env.batch_size, device=env.device)
    finished_impacts: list[torch.Tensor] = []

    if td is None:
        td = env.reset()
        env.stagger_episodes()
        # statistics from the first observations, so the first update is not on raw scales
        _update_normalizers(actor, critic, td)
    it = start
    budget_s = None if tc.max_minutes is None else 60.0 * tc.max_minutes
    # a time budget ends the run long before the iteration budget: show the time left, not a share of iterations
    bar_format = "{desc}: {n_fmt} it [{elapsed}, {rate_fmt}{postfix}]" if budget_s else None
    bar = tqdm(
        total=tc.iterations, initial=start, desc="train", unit="it", disable=not main_rank, dynamic_ncols=True,
        bar_format=bar_format,
    )  # fmt: skip
    try:
        while it < tc.iterations:
            t0 = time.perf_counter()
            # ---- collect ------------------------------------------------------------
            batch, td = collect(env, actor, td, tc.num_steps)
            # episode impact: worst contact force on any component, in newtons
            for t in range(tc.num_steps):
                episode_impact = torch.maximum(episode_impact, batch["next", "contact_force"][:, t].amax(dim=-1))
                done = batch["next", "done"][:, t].squeeze(-1)
                if done.any():
                    finished_impacts.append(episode_impact[done].clone())
                    episode_impact[done] = 0.0
            t1 = time.perf_counter()
            # ---- learn --------------------------------------------------------------
            torch.set_num_threads(update_threads)
            stats = ppo.update(batch, generator=shuffle)
            _update_normalizers(actor, critic, batch)
            torch.set_num_threads(collect_threads)
            t2 = time.perf_counter()
            it += 1

            # ---- log ----------------------------------------------------------------
            frames = batch.numel()
            stats.update(
                reward=batch["next", "reward"].mean().item(),
                collect_s=t1 - t0,
                update_s=t2 - t1,
                env_steps_per_s=frames * (dist.get_world_size() if distributed() else 1) / (t2 - t0),
                unstable=float(env.sim.num_unstable),
            )
            for name, value in env.pop_reward_terms().items():
                stats[f"reward_terms/{name}"] = value
            impacts = torch.cat(finished_impacts) if finished_impacts else torch.empty(0)
            stats["episode/max_impact_force"] = impacts.mean().item() if len(impacts) else float("nan")
            stats["episode/count"] = float(len(impacts))
            finished_impacts.clear()
            logger.log(it, stats)
            elapsed = time.monotonic() - started
            left = {} if budget_s is None else {"left": tqdm.format_interval(max(0, budget_s - elapsed))}
            bar.set_postfix(
                steps_s=f"{stats['env_steps_per_s']:.0f}",
                reward=f"{stats['reward']:.3f}",
                impact_N=f"{stats.get('episode/max_impact_force', float('nan')):.0f}",
                lr=f"{stats['learning_rate']:.1e}",
                **left,
                refresh=False,
            )
            bar.update(1)

            # ---- save ---------------------------------------------------------------
            out_of_time = budget_s is not None and elapsed > budget_s
            if main_rank and it % tc.checkpoint_every == 0:
                _save(ckpt_dir / f"iter_{it:06d}.pt", config, spec, it, env, td, actor, critic, ppo, shuffle)
            if stop.requested or out_of_time:
                if stop.requested:
                    log.warning("stopping on %s after iteration %d", stop.requested, it)
                else:
                    log.info("time budget of %g min reached after iteration %d", tc.max_minutes, it)
                break
    finally:
        bar.close()
        stop.restore()
    last = ckpt_dir / "last.pt"
    if main_rank:
        _save(last, config, spec, it, env, td, actor, critic, ppo, shuffle)
        logger.close()
        print(f"\ntrained {it} iterations in {(time.monotonic() - started) / 60:.1f} min; checkpoint: {last}")
        if it > start:
            from fallkit.plots import learning_curve

            curve = learning_curve(run_dir / "metrics.csv", run_dir / "learning_curve.png", f"{spec.name}: training")
            print(f"learning curve: {curve}")
    if distributed():
        _check_ranks_in_sync(actor)
    if main_rank and tc.evaluate and not stop.requested:
        _evaluate(config, run_dir, last)
    return last


# ---- pieces --------------------------------------------------------------------------


def collect(env, actor, td: TensorDict, num_steps: int) -> tuple[TensorDict, TensorDict]:
    """num_steps policy steps in every env: the [num_envs, num_steps] batch and the next step's input.

    TorchRL's step_and_maybe_reset restarts finished episodes (fresh initial state and end pose).
    """
    steps = []
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        for _ in range(num_steps):
            td = actor(td)
            td, next_td = env.step_and_maybe_reset(td)
            steps.append(td)
            td = next_td
    return torch.stack(steps, dim=1), td


def hold_prior(config: FallkitConfig, spec) -> HoldPrior | None:
    """The policy's hold prior for this robot and action scale, if the config asks for it."""
    if not config.train.hold_prior:
        return None
    start = 0
    for name, size in actor_layout(spec):
        if name == "joint_pos":
            break
        start += size
    columns = torch.arange(start, start + len(spec.joints))
    return HoldPrior(columns, torch.as_tensor(spec.nominal_q()), config.env.action_scale)


def _update_normalizers(actor, critic, batch: TensorDict) -> None:
    for norm, key in ((policy_net(actor).norm, "policy"), (value_net(critic).norm, "critic")):
        norm.update(batch[key])
        if distributed():  # average the statistics so every rank normalises alike
            stats = torch.cat([norm.mean, norm.var, norm.count.reshape(1)])
            dist.all_reduce(stats)
            stats /= dist.get_world_size()
            d = norm.mean.numel()
            norm.merge_(stats[:d], stats[d : 2 * d], stats[2 * d])


def _save(path: Path, config, spec, it, env, td, actor, critic, ppo, shuffle) -> None:
    save_checkpoint(
        path,
        {
            "config": config.model_dump(mode="json"),
            "robot": spec.name,
            "model_hash": spec.model_hash(),
            "iteration": it,
            "actor": actor.state_dict(),
            "critic": critic.state_dict(),
            "ppo": ppo.state_dict(),
            "env": env.run_state(),
            "observation": td.clone(),  # the next collection starts from it, noise included
            "rng": {"torch": torch.get_rng_state(), "shuffle": shuffle.get_state()},
        },
    )


def _resume(config, spec, env, actor, critic, ppo, shuffle) -> tuple[int, TensorDict]:
    ckpt = load_checkpoint(config.resume, map_location=env.device)
    if ckpt["robot"] != spec.name or ckpt["model_hash"] != spec.model_hash():
        raise CheckpointError(
            f"checkpoint {ckpt['path']} was trained on robot '{ckpt['robot']}' (model {ckpt['model_hash']}); "
            f"this run is '{spec.name}' (model {spec.model_hash()})"
        )
    try:
        actor.load_state_dict(ckpt["actor"])
        critic.load_state_dict(ckpt["critic"])
    except RuntimeError as exc:
        raise ConfigError(
            f"resume: network sizes differ from checkpoint {ckpt['path']} "
            f"(train.actor_hidden / train.critic_hidden): {str(exc).splitlines()[0]}"
        ) from None
    ppo.load_state_dict(ckpt["ppo"])
    try:
        env.load_run_state(ckpt["env"])
    except ValueError as exc:
        raise ConfigError(f"resume: {exc}") from None
    torch.set_rng_state(ckpt["rng"]["torch"])
    shuffle.set_state(ckpt["rng"]["shuffle"])
    log.info("resumed from %s at iteration %d", ckpt["path"], ckpt["iteration"])
    return int(ckpt["iteration"]), ckpt["observation"].to(env.device)


def _evaluate(config: FallkitConfig, run_dir: Path, checkpoint: Path) -> None:
    """The training run ends by evaluating its final policy against the standard strategies."""
    from fallkit.evaluate import evaluate_checkpoint

    evaluate_checkpoint(config, run_dir, checkpoint)


def _check_ranks_in_sync(actor) -> None:
    """Every rank must end with the same weights (gradients were averaged); say so, or fail loudly."""
    flat = torch.cat([p.detach().reshape(-1).double() for p in actor.parameters()])
    mine = torch.stack([flat.sum(), flat.square().sum()])
    gathered = [torch.zeros_like(mine) for _ in range(dist.get_world_size())]
    dist.all_gather(gathered, mine)
    if any(not torch.equal(g, gathered[0]) for g in gathered):
        raise RuntimeError("distributed training: ranks ended with different weights")
    if dist.get_rank() == 0:
        log.info("distributed training: weights identical on %d ranks", dist.get_world_size())
    dist.barrier()


def _init_distributed(config: FallkitConfig) -> int:
    """Join the torchrun group when launched by torchrun; return this process's rank."""
    if int(os.environ.get("WORLD_SIZE", "1")) <= 1 or distributed():
        return dist.get_rank() if distributed() else 0
    backend = "nccl" if config.sim.device.startswith("cuda") and torch.cuda.is_available() else "gloo"
    dist.init_process_group(backend=backend)
    return dist.get_rank()


class _StopFlag:
    """SIGINT/SIGTERM ask the loop to stop after the current iteration (and save)."""

    def __init__(self):
        self.requested: str | None = None
        self._previous = {}
        for sig in (signal.SIGINT, signal.SIGTERM):
            try:
                self._previous[sig] = signal.signal(sig, self._handle)
            except ValueError:  # not the main thread
                pass

    def _handle(self, signum, frame) -> None:
        if self.requested:  # a second signal: stop at once
            raise KeyboardInterrupt
        self.requested = signal.Signals(signum).name

    def restore(self) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)


class _Logger:
    """TensorBoard scalars and a CSV of the same figures, one row per iteration."""

    def __init__(self, run_dir: Path, enabled: bool):
        self.enabled = enabled
        if not enabled:
            return
        from torch.utils.tensorboard import SummaryWriter

        self.tb = SummaryWriter(str(run_dir / "tensorboard"))
        self.csv_path = run_dir / "metrics.csv"
        self._file = None
        self._writer = None
        self._fields: list[str] | None = None

    def log(self, it: int, stats: dict[str, float]) -> None:
        if not self.enabled:
            return
        for k, v in stats.items():
            self.tb.add_scalar(k, v, it)
        row = {"iteration": it, **stats}
        if self._writer is None:
            new = not self.csv_path.exists()
            self._file = open(self.csv_path, "a", newline="")
            self._fields = list(row)
            self._writer = csv.DictWriter(self._file, fieldnames=self._fields, extrasaction="ignore")
            if new:
                self._writer.writeheader()
        self._writer.writerow({k: row.get(k, "") for k in self._fields})
        self._file.flush()

    def close(self) -> None:
        if self.enabled:
            self.tb.close()
            if self._file:
                self._file.close()
