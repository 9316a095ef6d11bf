"""`mode=eval`: a policy against the standard fall strategies, with the paper's metrics.

Paired comparison (paper Sec. V-C, `fallkit.eval.rollout`): every strategy falls
from the same initial states toward the same end poses, in one FallEnv whose
worlds hold one block per strategy; trials beyond one env's worlds run in
chunks. Evaluation runs without observation noise and disturbance forces, so
the comparison is deterministic and stays paired.

Outputs in the run dir (`fallkit.eval.report`): eval.json (one object per
strategy), eval.md (tables), eval_trials.npz (every per-trial figure) and the
PNG plots of `fallkit.eval.plots`.

eval.poses=auto (`fallkit.eval.choice`): the same falls run twice, toward randomly
assigned candidates and toward the candidate chosen for each fall when it begins;
the tables are the chosen poses', eval.json's `end_pose_choice` compares the two.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from tensordict.nn import TensorDictModuleBase

from fallkit.config import FallkitConfig, RobotConfig
from fallkit.env.build import make_env
from fallkit.env.fall_env import FallEnv
from fallkit.errors import ConfigError
from fallkit.eval.choice import PoseChoice, choice_line, choose_end_poses, compare, restrict
from fallkit.eval.report import ratio_line, text_table, write_results
from fallkit.eval.rollout import POLICY, SEEK, Rollout, Trials, chunking, draw_trials, evaluate, rollout
from fallkit.eval.strategies import STRATEGIES
from fallkit.poses import load_end_poses
from fallkit.rl.policy import load_policy
from fallkit.robots import robot_spec

# mode=eval's whole surface, the paired rollouts and the reports included
__all__ = [
    "POLICY", "SEEK", "EvalSetup", "Rollout", "Trials", "chunking", "draw_trials", "eval_run_config", "evaluate",
    "evaluate_checkpoint", "make_eval_env", "prepare", "rollout", "run_eval", "text_table", "write_results",
]  # fmt: skip

log = logging.getLogger(__name__)


@dataclass
class EvalSetup:
    """What eval and render share: the config the env is built from, the policy (if any)
    and where the end poses come from."""

    config: FallkitConfig  # of the env: the training run's (with a checkpoint), this run's sim
    policy: TensorDictModuleBase | None  # "policy" -> "action"
    checkpoint: str | None
    poses: str  # end-pose source (dataset, pose file or "default"); with eval.poses=auto the candidates'
    split: str
    seek_reference: bool = False
    choice: PoseChoice | None = None  # eval.poses=auto: how each fall's end pose is chosen from `poses`

    @property
    def strategies(self) -> list[str]:
        """The policy (if any) and the paper's standard strategies."""
        return ([POLICY] if self.policy is not None else []) + list(STRATEGIES)

    @property
    def compared(self) -> list[str]:
        """What mode=eval runs: the strategies, then the seek reference if asked for."""
        return self.strategies + ([SEEK] if self.seek_reference else [])


def prepare(config: FallkitConfig) -> EvalSetup:
    """Load the checkpoint (if any) and decide the end poses named by `config.eval`.

    With a checkpoint the env is built from the training run's config (robot,
    sensitivity, env and reward settings: the observations must match what the
    policy learned on), with this run's simulator settings. With eval.poses=auto the poses
    are the candidates (eval.candidates) and `choice` says how each fall's is chosen; the
    critic scorer needs a checkpoint, which is checked here, before anything is simulated.
    """
    ev = config.eval
    run_config, policy, critic = config, None, None
    if ev.poses == "auto" and ev.scorer == "critic" and config.checkpoint is None:
        raise ConfigError(
            "eval.poses=auto with eval.scorer=critic ranks the end poses by a trained critic: give "
            "checkpoint=<run dir>, or choose by where the fall heads with eval.scorer=heading"
        )
    if config.checkpoint is not None:
        loaded = load_policy(config.checkpoint)
        policy, critic = loaded.module, loaded.critic
        trained = loaded.config
        if trained.robot.name != config.robot.name:
            hint = f"; add robot={trained.robot.name} to set its sensitivity weights"
            log.warning("evaluating the checkpoint's robot '%s' (robot=%s is ignored%s)", trained.robot.name,
                        config.robot.name, hint if trained.env.sensitivity_inputs.enabled else "")  # fmt: skip
        if trained.seed == ev.seed:
            raise ConfigError(
                f"eval.seed: {ev.seed} is the training seed of {config.checkpoint}; "
                "evaluation needs initial states never used in training"
            )
        run_config = trained.model_copy(update={"sim": config.sim, "robot": _evaluated_robot(trained, config)})
    if ev.poses == "auto":
        poses = ev.candidates if ev.candidates is not None else run_config.env.poses
        critic = critic if ev.scorer == "critic" else None
        choice = PoseChoice(ev.scorer, ev.candidate_side, critic, ev.heading_pivot_height)
        return EvalSetup(run_config, policy, config.checkpoint, poses, ev.split, ev.seek_reference, choice)
    poses = ev.poses if ev.poses is not None else run_config.env.poses
    return EvalSetup(run_config, policy, config.checkpoint, poses, ev.split, ev.seek_reference)


def _evaluated_robot(trained: FallkitConfig, config: FallkitConfig) -> RobotConfig:
    """The robot a checkpoint is evaluated on: the training run's, with this run's sensitivity weights
    where the policy observes them (env.sensitivity_inputs: `robot.sensitivity.head=4` changes what it does)."""
    if not trained.env.sensitivity_inputs.enabled or trained.robot.name != config.robot.name:
        return trained.robot
    weights = {**trained.robot.sensitivity, **config.robot.sensitivity}
    changed = {k: w for k, w in weights.items() if trained.robot.sensitivity.get(k) != w}
    if changed:
        log.info("the policy observes sensitivity weights: evaluating with %s (trained around %s)", changed,
                 {k: trained.robot.sensitivity.get(k) for k in changed})  # fmt: skip
    drawn = trained.env.sensitivity_inputs.components
    fixed = sorted(k for k in changed if drawn is not None and k not in drawn)
    if fixed:
        log.warning("the policy was trained with only %s drawn (env.sensitivity_inputs.components): it never saw "
                    "another weight of %s, so what it does with one is untested", drawn, fixed)  # fmt: skip
    return trained.robot.model_copy(update={"sensitivity": weights})


def eval_run_config(config: FallkitConfig, seconds: float | None) -> FallkitConfig:
    """The run config an evaluation env is built from (see make_eval_env)."""
    env = config.env
    env_update: dict[str, Any] = {
        "noise": env.noise.model_copy(update={"scale": 0.0}),
        "disturbances": env.disturbances.model_copy(update={"enabled": False}),
        "randomization": type(env.randomization)(),  # nominal friction, gains and timing
        "pose_fraction": 1.0,  # a dataset-size ablation subsamples training poses, never the test split
        # a policy with sensitivity inputs observes the robot's weights (robot.sensitivity), none drawn
        "sensitivity_inputs": env.sensitivity_inputs.model_copy(update={"low": 1.0, "high": 1.0}),
    }
    if seconds is not None:
        env_update["episode_length"] = seconds
    # Rewards play no part in the metrics: weight 0 switches every term off (not computed),
    # which saves a good part of each env step. blend_time only has to pass the env's check.
    reward = type(config.reward).model_validate(
        {
            **config.reward.model_dump(),
            **{name: 0.0 for name in config.reward.weights()},
            "blend_time": min(config.reward.blend_time, env_update.get("episode_length", env.episode_length)),
        }
    )
    return config.model_copy(update={"env": env.model_copy(update=env_update), "reward": reward})


def make_eval_env(setup: EvalSetup, num_envs: int, seconds: float | None, seed: int) -> FallEnv:
    """The run's FallEnv (fallkit.env.build) for evaluation: no observation noise, no disturbances,
    no reward terms, the whole end-pose split, falls of `seconds` (None: the env's episode length).
    With eval.poses=auto its end poses are the candidates, restricted to eval.candidate_side."""
    cfg = eval_run_config(setup.config, seconds)
    spec = robot_spec(cfg.robot)
    if setup.choice is not None and setup.choice.sides:
        poses = restrict(load_end_poses(setup.poses, spec, split=setup.split), setup.choice.sides, _pose_note(setup))
        return make_env(cfg, spec, seed=seed, num_envs=num_envs, end_poses=poses)
    return make_env(cfg, spec, split=setup.split, seed=seed, num_envs=num_envs, poses=setup.poses)


def evaluate_checkpoint(config: FallkitConfig, run_dir: Path, checkpoint: str | Path) -> dict:
    """Evaluate a checkpoint with `config.eval` into run_dir (the end of a training run)."""
    return run_eval(config.model_copy(update={"checkpoint": str(checkpoint)}), run_dir)


def run_eval(config: FallkitConfig, run_dir: Path) -> dict:
    """`mode=eval`: evaluate, write the results into run_dir, print the table."""
    ev = config.eval
    torch.set_num_threads(1)  # the physics threads are MuJoCo's (2 torch threads beside them measured 1.5-1.8x slower)
    setup = prepare(config)
    strategies = setup.compared
    k, chunks = chunking(ev.trials, len(strategies), config.sim.num_envs)
    env = make_eval_env(setup, len(strategies) * k, ev.seconds, ev.seed)
    trials = draw_trials(env, ev.trials, ev.seed)
    log.info(
        "eval %s: %d trials × %s, %d chunk(s) of %d worlds, %.2f s falls",
        env.spec.name, ev.trials, ", ".join(strategies), chunks, env.num_envs, env.max_steps * env.dt,
    )  # fmt: skip
    t0 = time.perf_counter()
    results = evaluate(env, trials, strategies, setup.policy)
    poses = f"{setup.poses} ({_split_note(setup)}{len(env.end_poses)} poses)"
    choice = random = None
    if setup.choice is not None:  # the same falls again, toward the chosen poses
        random, t1 = results, time.perf_counter()
        chosen = choose_end_poses(env, trials, setup.choice)
        choosing = time.perf_counter() - t1
        results = evaluate(env, chosen, strategies, setup.policy)
        choice = compare(random, results, trials.pose_ids, chosen.pose_ids, env.end_poses, setup.choice, poses)
        choice["seconds_to_choose"] = choosing
        poses = f"auto, chosen by {setup.choice.scorer} from {poses}" + (
            f" lying on {'/'.join(setup.choice.sides)}" if setup.choice.sides else "")
    info = {
        "robot": env.spec.name,
        "checkpoint": setup.checkpoint,
        "trials": ev.trials,
        "seconds": env.max_steps * env.dt,
        "seed": ev.seed,
        "poses": poses,
        "elapsed": time.perf_counter() - t0,
    }
    summary = write_results(results, env.spec.component_names, info, Path(run_dir), choice, random)
    strategies_only = {name: summary[name] for name in results}
    print()
    print(text_table(strategies_only))
    if POLICY in summary:
        print(ratio_line(strategies_only))
    if choice is not None:
        print(choice_line(choice, POLICY if POLICY in results else strategies[0]))
    print(f"\n{ev.trials} falls × {len(strategies)} strategies in {info['elapsed']:.1f} s; results in {run_dir}/eval.md")
    return summary


def _pose_note(setup: EvalSetup) -> str:
    """Where the end poses come from, for messages: e.g. "default (test split)"."""
    split = _split_note(setup)
    return f"{setup.poses} ({split.removesuffix(', ')})" if split else setup.poses


def _split_note(setup: EvalSetup) -> str:
    """Pose files have no splits; datasets do."""
    artist = setup.poses == "artist" or Path(setup.poses).suffix in (".yaml", ".yml")
    return "" if artist else f"{setup.split} split, "
