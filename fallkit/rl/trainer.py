"""`mode=train`: PPO on the batched falling environment (paper Sec. V-A, Table III).

`Trainer.run()` is the whole loop, one iteration per pass, read top to bottom:
  collect   num_steps policy steps in every env (FallEnv's step_and_maybe_reset:
            finished envs restart: a fresh initial state and end pose, or a stored one, train.level_replay)
  learn     PPO.update: GAE, epochs x minibatches of ClipPPOLoss, adaptive lr (+ train.self_imitation,
            + train.teachers' imitation term); then
            merge the batch into the running observation statistics (after the
            update, so the update saw the statistics the data was collected with)
  log       progress bar, TensorBoard scalars, metrics.csv
  save      checkpoints/iter_<k>.pt every checkpoint_every iterations and last.pt at
            the end, atomically; SIGINT/SIGTERM finish the iteration, save, and stop.
A checkpoint is `Trainer.state_dict()`; `load_state_dict` continues a run exactly.

Under torchrun each rank steps its own envs with its own seed; gradients, KL and
observation statistics are averaged over ranks; rank 0 logs and saves.
"""

from __future__ import annotations

import logging
import math
import time
from pathlib import Path
from typing import Any

import torch
import torch.distributed as dist
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type

from fallkit.config import FallkitConfig
from fallkit.env.build import make_env
from fallkit.env.fall_env import FallEnv
from fallkit.env.mirror import ObservationMirror, observation_mirror
from fallkit.errors import CheckpointError, ConfigError, TrainingError
from fallkit.machine import core_share, running_processes, subnormals_flushed
from fallkit.rl.checkpoint import checkpoint_run_dir, load_checkpoint, run_checkpoints, save_checkpoint, shape_mismatch
from fallkit.rl.exploration import CorrelatedNoise
from fallkit.rl.init_from import fresh_statistics, start_from
from fallkit.rl.models import joint_prior, make_actor, policy_net, resolve_precision, value_net
from fallkit.rl.monitor import EpisodeImpacts, MetricsLog, Progress, StopFlag
from fallkit.rl.ppo import PPO
from fallkit.rl.ranks import (
    any_over_ranks, averaged_over_ranks, check_ranks_in_sync, distributed, init_distributed, merge_over_ranks, world_size
)
from fallkit.rl.relabel import EndPoseRelabel, SensitivityRelabel
from fallkit.rl.reward_schedule import RewardSchedule
from fallkit.rl.self_imitation import make_self_imitation
from fallkit.rl.shaping import OrientationPotential
from fallkit.rl.teachers import Teachers
from fallkit.rl.value_heads import critic_for
from fallkit.robots import robot_spec

log = logging.getLogger(__name__)


class Trainer:
    """One training run: env, actor, critic, PPO and everything needed to continue it exactly."""

    def __init__(self, config: FallkitConfig, run_dir: Path):
        tc = config.train
        self.config, self.run_dir = config, Path(run_dir)
        self.rank = init_distributed(config.sim.device)
        # MuJoCo's threads own the cores while collecting; the update has this process's share
        # of them to itself (fallkit.machine: asked again every iteration)
        self.collect_threads, self.update_threads = 1, tc.torch_threads or core_share()
        torch.set_num_threads(self.collect_threads)
        seed = config.seed + 1_000_003 * self.rank
        torch.manual_seed(seed)
        self.spec = robot_spec(config.robot)
        # before anything is built: a robot without a mirror map is a one-line config error
        mirror = observation_mirror(
            self.spec, sensitivity=config.env.sensitivity_inputs.enabled, gravity=config.env.observe_gravity
        ) if tc.ppo.mirror else None
        self.env = make_env(config, self.spec, split="train", seed=seed)
        self.env.shorten_episodes(tc.short_episodes)
        self.replay = self.env.replay_levels(tc.level_replay) if tc.level_replay.share > 0 else None
        precision = resolve_precision(tc.precision, self.env.device)
        if precision != tc.precision:  # checkpoints record the arithmetic the policy learned with, not "auto"
            config = config.model_copy(update={"train": tc.model_copy(update={"precision": precision})})
            self.config, tc = config, config.train
        log.info("networks compute in %s (train.precision)", precision)
        obs_dim, critic_dim = (self.env.observation_spec[k].shape[-1] for k in ("policy", "critic"))
        act_dim = self.env.action_spec.shape[-1]
        prior = joint_prior(config, self.spec)
        self.actor = make_actor(
            obs_dim, act_dim, tc.actor_hidden, tc.init_noise_std, prior, noise_floor=tc.fade_noise, precision=tc.precision
        ).to(self.env.device)
        self.critic, heads = critic_for(config, self.spec, self.env.rewards, critic_dim, tc.precision)
        self.critic = self.critic.to(self.env.device)
        # checked with the replay off too: a misspelt score is an error, not a value waiting to bite later
        self.replay_column = _replay_column(tc.level_replay.score, heads)
        self.new_columns, start_rate = None, None  # train.init_from: the loaded networks' new inputs, rate
        if tc.init_from and not config.resume:
            self.new_columns, start_rate = start_from(
                tc.init_from, self.actor, self.critic, config, self.spec, self.env.device
            )
        if distributed():  # every rank starts from rank 0's weights (as DistributedDataParallel does)
            for tensor in [*self.actor.state_dict().values(), *self.critic.state_dict().values()]:
                dist.broadcast(tensor, src=0)
        self.ppo = self._make_ppo(mirror)
        self.reward_schedule = RewardSchedule(tc, self.env.rewards, value_net(self.critic), heads)
        self.self_imitation = make_self_imitation(
            config, self.actor, self.critic, self.env.rewards, heads, self.env.num_envs, self.env.max_steps
        )
        if start_rate is not None:
            self.ppo.optimizer.start_at(start_rate)
        self.shuffle = torch.Generator().manual_seed(seed)
        self.noise = CorrelatedNoise(
            self.env.num_envs, act_dim, tc.noise_correlation_time, self.env.dt, self.env.device
        ) if tc.noise_correlation_time > 0 else None  # fmt: skip
        self.iteration, self.start = 0, 0
        self.td: TensorDict | None = None  # the next collection's input
        self.impacts = EpisodeImpacts(self.env)
        self.stopped: str | None = None  # the signal that stopped the run, if one did
        self.resumed_from: Path | None = None  # the run directory of the checkpoint resumed
        position = self._resume(config.resume) if config.resume else None  # the reward schedule's, where kept
        in_table_units = bool(tc.init_from and not config.resume)
        self.reward_schedule.start(self.env_steps, self.steps_per_iteration, in_table_units, position)

    def _resume(self, path: str) -> float | None:
        """Continue the checkpoint at `path` (config.resume): its iteration, weights, optimiser and env state;
        returns the reward schedule's position it kept (None: a checkpoint from before it was kept)."""
        ckpt = load_checkpoint(path, map_location=self.env.device)
        self.load_state_dict(ckpt)
        self.start = self.iteration
        self.resumed_from = checkpoint_run_dir(ckpt["path"])
        if self.main_rank:
            target = self.config.train.iterations
            print(f"resumed from {ckpt['path']} at iteration {self.iteration}; training to {target}")
        return ckpt.get("reward_schedule_position")

    def _make_ppo(self, mirror: ObservationMirror | None) -> PPO:
        """PPO over this run's actor and critic, with the learning aids the config switches on."""
        config, ppo = self.config, self.config.train.ppo
        sensitivity, gravity = config.env.sensitivity_inputs, config.env.observe_gravity
        potential = OrientationPotential(
            self.spec, ppo.orientation_potential, sensitivity.enabled, gravity
        ) if ppo.orientation_potential > 0 else None  # fmt: skip
        relabels = [SensitivityRelabel(self.spec, sensitivity, self.env.rewards, gravity)] if ppo.relabel_sensitivity else []
        if ppo.relabel_end_pose:
            tilt, joints = self.env.end_pose_goals()
            relabels.append(EndPoseRelabel(
                self.spec, tilt, joints, self.env.rewards, self.env.max_steps * self.env.dt, config.reward.blend_time,
                sensitivity.enabled, gravity,
            ))  # fmt: skip
        mirror = mirror.to(self.env.device) if mirror else None
        taught = config.train.teachers
        teachers = Teachers(config, self.spec, self.env.device) if taught.runs else None
        return PPO(self.actor, self.critic, ppo, mirror, potential, self.env.rewards, relabels, teachers, taught.coef)

    @property
    def main_rank(self) -> bool:
        return self.rank == 0

    @property
    def steps_per_iteration(self) -> int:
        """Env steps one iteration collects (all worlds, all ranks)."""
        return self.env.num_envs * self.config.train.num_steps * world_size()

    @property
    def env_steps(self) -> int:
        """Env steps collected so far: the clock of the training schedules."""
        return self.iteration * self.steps_per_iteration

    def run(self) -> Path:
        """Train until the iteration budget, the time budget or a stop signal; returns the last checkpoint."""
        tc = self.config.train
        metrics, stop = MetricsLog(self.run_dir, self.main_rank, self.start, self.resumed_from), StopFlag()
        progress = Progress(tc.iterations, self.iteration, tc.max_minutes, self.main_rank)
        try:
            while self.iteration < tc.iterations:
                # the budget's share spent, for the reward schedule where it counts it (the ranks' clocks differ)
                spent = averaged_over_ranks(progress.spent, self.env.device) if self.reward_schedule.within_budget else 0.0
                stats = self.iterate(spent)
                metrics.log(self.iteration, stats)
                finite = math.isfinite(stats["loss_objective"]) and math.isfinite(stats["loss_critic"])
                # every rank stops at the same iteration, whichever rank's reason it was
                signalled, out_of_time, diverged = any_over_ranks(
                    (bool(stop.requested), progress.out_of_time, not finite), self.env.device
                )
                if diverged:
                    self._diverged(stats, finite)
                progress.update(stats)
                if self.main_rank and self.iteration % tc.checkpoint_every == 0:
                    self.save(self.run_dir / "checkpoints" / f"iter_{self.iteration:06d}.pt")
                if signalled or out_of_time:
                    self._say_why_it_stopped(stop.requested or ("a signal to another rank" if signalled else None))
                    break
        finally:
            progress.close()
            stop.restore()
            metrics.close()
        return self._finish(progress.elapsed)

    # ---- the steps of one iteration ---------------------------------------------------

    def iterate(self, budget_spent: float = 0.0) -> dict[str, float]:
        """Collect, learn, and the iteration's figures, read from the device once (a read waits for
        the device's queue: once per iteration, after the update, so `update_s` is its real time).
        `budget_spent`: the share (0-1) of the run's iterations or minutes gone, for the reward schedule."""
        t0 = time.perf_counter()
        factors = self.reward_schedule.step(self.env_steps, budget_spent)
        batch = self.collect()
        t1 = time.perf_counter()
        stats = self.learn(batch) | self.diagnostics(batch)
        stats = dict(zip(stats, torch.stack([v.to(torch.float64) for v in stats.values()]).tolist()))
        t2 = time.perf_counter()
        self.iteration += 1
        stats["collect_s"], stats["update_s"] = t1 - t0, t2 - t1
        stats["env_steps_per_s"] = batch.numel() * world_size() / (t2 - t0)
        stats["unstable"] = float(self.env.sim.num_unstable)  # a count kept on the host
        return stats | factors

    def collect(self) -> TensorDict:
        """num_steps policy steps in every env: the [num_envs, num_steps] batch."""
        if self.td is None:  # a new run (a resumed one continues from its checkpoint's observation)
            self.td = self._first_observation()
        batch, self.td = collect(self.env, self.actor, self.td, self.config.train.num_steps, self.noise)
        self.impacts.add(batch)
        return batch

    def learn(self, batch: TensorDict) -> dict[str, torch.Tensor]:
        """The PPO update on this process's share of the cores, then the batch into the running observation statistics."""
        self._share_cores()
        torch.set_num_threads(self.update_threads)
        with subnormals_flushed():  # else the update slows as the critic saturates (fallkit.machine)
            minibatches = self.config.train.ppo.minibatches_at(self.env_steps)
            stats = self.ppo.update(batch, generator=self.shuffle, num_minibatches=minibatches)
        if self.replay is not None:  # the update's advantages score the falls the batch played
            column = self.replay_column
            score = batch["advantage"] if column is None else batch["term_advantages"][..., column]
            stats |= self.replay.record(batch["fall_id"], score)
        if self.self_imitation is not None:  # after PPO: the returns are judged by the updated critic
            self.self_imitation.add(batch)
            stats |= self.self_imitation.update(self.shuffle)
        _update_normalizers(self.actor, self.critic, batch, self.ppo.mirror)
        torch.set_num_threads(self.collect_threads)
        return stats

    def _share_cores(self) -> None:
        """The update's torch threads: train.torch_threads, or this process's share of the cores now."""
        if self.config.train.torch_threads:
            return
        share = core_share()
        if share != self.update_threads:
            log.info("cores: %d fallkit processes running; the update now uses %d threads", running_processes(), share)
            self.update_threads = share

    def diagnostics(self, batch: TensorDict) -> dict[str, torch.Tensor]:
        """The batch's reward, each reward term's and the finished episodes' impacts, on the device."""
        stats = {"reward": batch["next", "reward"].mean()}
        terms = self.env.rewards.pop_mean_tensor()
        if terms is not None:
            stats.update({f"reward_terms/{name}": v for name, v in zip(self.env.rewards.names, terms)})
        return stats | self.impacts.pop()

    def save(self, path: Path) -> None:
        save_checkpoint(path, self.state_dict())

    # ---- checkpoints --------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to continue exactly, and what evaluation needs to rebuild the policy."""
        return {
            "config": self.config.model_dump(mode="json"),
            "robot": self.spec.name,
            "model_hash": self.spec.model_hash(),
            "iteration": self.iteration,
            "actor": self.actor.state_dict(),
            "critic": self.critic.state_dict(),
            "head_factors": self.reward_schedule.head_factors(),  # the critic's heads' reward-weight factors
            "reward_schedule_position": self.reward_schedule.position,
            "ppo": self.ppo.state_dict(),
            "env": self.env.run_state(),
            "observation": self.td.clone(),  # the next collection starts from it, noise included
            "rng": {"torch": torch.get_rng_state(), "shuffle": self.shuffle.get_state()},
            "noise": self.noise.state_dict() if self.noise is not None else None,
            "self_imitation": self.self_imitation.state_dict() if self.self_imitation is not None else None,
        }

    def load_state_dict(self, ckpt: dict[str, Any]) -> None:
        """Continue from a checkpoint of the same robot, network sizes and number of envs."""
        path = ckpt.get("path", "the checkpoint")
        if ckpt["robot"] != self.spec.name or ckpt["model_hash"] != self.spec.model_hash():
            raise CheckpointError(
                f"checkpoint {path} was trained on robot '{ckpt['robot']}' (model {ckpt['model_hash']}); "
                f"this run is '{self.spec.name}' (model {self.spec.model_hash()})"
            )
        for name, net in (("actor", self.actor), ("critic", self.critic)):
            differ = shape_mismatch(net.state_dict(), ckpt[name])
            if differ:
                raise ConfigError(
                    f"resume: the {name} network of {path} differs from this run's: {differ}; "
                    f"the run had train.{name}_hidden={ckpt['config']['train'][f'{name}_hidden']}: drop the override"
                )
            net.load_state_dict(ckpt[name])
        self.ppo.load_state_dict(ckpt["ppo"])
        try:
            self.env.load_run_state(ckpt["env"])
        except ValueError as exc:
            raise ConfigError(f"resume: {exc}") from None
        torch.set_rng_state(ckpt["rng"]["torch"])
        self.shuffle.set_state(ckpt["rng"]["shuffle"])
        if self.noise is not None and ckpt.get("noise") is not None:  # else: a fresh stationary draw
            self.noise.load_state_dict(ckpt["noise"])
        if self.self_imitation is not None and ckpt.get("self_imitation") is not None:  # else: an empty store
            self.self_imitation.load_state_dict(ckpt["self_imitation"])
        self.iteration = int(ckpt["iteration"])
        self.td = ckpt["observation"].to(self.env.device)

    # ---- start and end ------------------------------------------------------------------

    def _first_observation(self) -> TensorDict:
        td = self.env.reset()
        self.env.stagger_episodes()
        # statistics from the first observations, so the first update is not on raw scales
        if self.new_columns is not None:
            fresh_statistics(policy_net(self.actor).norm, self.new_columns.policy, td["policy"])
            fresh_statistics(value_net(self.critic).norm, self.new_columns.critic, td["critic"])
        _update_normalizers(self.actor, self.critic, td, self.ppo.mirror)
        return td

    def _diverged(self, stats: dict[str, float], finite_here: bool) -> None:
        """Stop at the first iteration whose losses are NaN or infinite (on any rank): the weights are then
        too, and every iteration after it (and a last.pt of them) would be wasted; the periodic checkpoints stay."""
        kept = run_checkpoints(self.run_dir)
        where = f"the last checkpoint before it is {kept[0]}" if kept else "no checkpoint was saved before it"
        loss = "on another rank" if finite_here else f"{stats['loss_objective']} (value loss {stats['loss_critic']})"
        raise TrainingError(
            f"training diverged at iteration {self.iteration}: the PPO loss is {loss}; metrics.csv has the "
            f"iterations before it and {where}: resume from it with a smaller train.ppo.desired_kl or without "
            "the last learning aid switched on"
        )

    def _say_why_it_stopped(self, signal_name: str | None) -> None:
        if signal_name:
            self.stopped = signal_name
            log.warning("stopping on %s after iteration %d", signal_name, self.iteration)
        else:
            log.info("time budget of %g min reached after iteration %d", self.config.train.max_minutes, self.iteration)

    def _finish(self, elapsed_s: float) -> Path:
        last = self.run_dir / "checkpoints" / "last.pt"
        if self.main_rank:
            self.save(last)
            print(f"\ntrained {self.iteration} iterations in {elapsed_s / 60:.1f} min; checkpoint: {last}")
        if distributed():
            check_ranks_in_sync(self.actor)
        return last


def collect(
    env: FallEnv, actor, td: TensorDict, num_steps: int, noise: CorrelatedNoise | None = None
) -> tuple[TensorDict, TensorDict]:
    """num_steps policy steps in every env: the [num_envs, num_steps] batch and the next step's input.

    FallEnv's step_and_maybe_reset (TorchRL's contract, one host read per step) restarts finished
    episodes (fresh initial state and end pose).
    With `noise` the actions explore with noise correlated in time (train.noise_correlation_time).
    """
    steps = []
    with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
        for _ in range(num_steps):
            if noise is None:
                td = actor(td)
            else:  # loc and scale only (get_dist draws nothing); the noise draws the action
                actor.get_dist(td)
                td = noise.act(td, fresh=env.episode_starts())
            td, next_td = env.step_and_maybe_reset(td)
            steps.append(td)
            td = next_td
    return torch.stack(steps, dim=1), td


def _update_normalizers(actor, critic, batch: TensorDict, mirror: ObservationMirror | None = None) -> None:
    """The batch into the running statistics; with mirror augmentation its mirror image too, so the
    statistics are symmetric and a mirrored fall is normalised as the mirror image of the original."""
    for norm, key in ((policy_net(actor).norm, "policy"), (value_net(critic).norm, "critic")):
        obs = batch[key]
        if mirror is not None:
            flip = mirror.actor if key == "policy" else mirror.critic
            obs = torch.cat([obs, flip(obs)])
        norm.update(obs)
        merge_over_ranks(norm)


def _replay_column(score: str, heads: list[str]) -> int | None:
    """train.level_replay.score: None for the actor's advantage, else the value head whose advantage scores a play."""
    if score == "advantage":
        return None
    if score not in heads:
        raise ConfigError(
            f"train.level_replay.score={score} is not a reward term with a value head of its own (heads: "
            f"{', '.join(heads)}): use 'advantage', or a reward term with train.ppo.value_per_term=true"
        )
    return heads.index(score)
