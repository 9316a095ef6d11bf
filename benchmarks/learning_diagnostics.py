"""Where a trained policy loses the end pose, and whether the task's reward agrees (issue 13).

Reads a finished training run (its checkpoint and the per-fall results `eval_trials.npz` of its
evaluation) and answers five questions on the same falls its evaluation used:

1. **Which falls**: seek (the open-loop blend to the target joints, no learning) lands some falls
   within 0.5 rad of the target tilt ("easy") and ends others beyond 2 rad ("hard"). What share
   of the easy ones does the policy keep, and what share of the hard ones does it fix? And the other
   way round (`seek_keeps_policys`): of the falls the policy lands within 0.5 rad, what share does seek
   land? "Easy" is chosen by seek's own outcome, so a policy as good as seek but not seek keeps fewer of
   them whenever small differences change where a fall ends; the two shares alike say that is what the
   loss is, not a habit of the policy.
2. **What the reward says**: the policy and seek replayed on those falls with the training
   reward switched on (the evaluation switches it off): undiscounted return, split into the
   orientation term and all the rest, per group. If the policy's return is lower where it loses
   the pose, the reward would pay to keep it — the shortfall is learning, not the reward.
3. **Does the learned deviation read the goal**: along the policy's own falls, the change of the
   learned deviation (the MLP's share of the action) when each fall's end pose is replaced by
   another fall's, relative to its size, by time; and its size, Σ_j d_j² averaged over the falls' steps
   (`deviation_sq`: what `prior_deviation` in metrics.csv averages over the training samples, and what
   train.ppo.prior_coef penalises).
4. **Does the training's own noise hide the easy falls**: the policy's mean and seek replayed on the same
   falls with Gaussian action noise at the policy's trained std added at every step (what training explores
   with; the evaluation has none), `--noise-repeats` times each: the shares of seek's easy falls each keeps
   and of the hard ones each fixes (`under_noise`). If seek under that noise lost its easy falls as often as
   the policy loses them, the training falls would not show that the prior lands them.
5. **When does the policy steer**: along the same replays, the angle between the root's up axis and the end
   pose's (the orientation term's tilt, as an angle) averaged over the falls, by time, for the policy and
   seek (`tilt_error_by_time`). A policy that only chooses the side in the air lowers it before landing
   (~0.7 s); one that rolls over on the ground lowers it until its learned deviation fades (T_blend).

    python benchmarks/learning_diagnostics.py RUN_DIR   # e.g. runs/learning_power8/<time>/seed0

The last line is one JSON object (`easy_kept`, `hard_fixed`, `seek_keeps_policys`, `returns`, `goal_dependence`,
`deviation_sq`, `under_noise`, `tilt_error_by_time`).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
import yaml

from fallkit.config import validate
from fallkit.env.build import make_env
from fallkit.env.observations import actor_slices
from fallkit.eval.evaluate import eval_run_config, prepare
from fallkit.eval.metrics import mroe
from fallkit.eval.rollout import draw_trials, seek_action
from fallkit.rl.shaping import OrientationPotential
from fallkit.robots import robot_spec

EASY, HARD = 0.5, 2.0  # [rad] seek's final orientation error: lands right / ends on another side


def fall_groups(trials: np.lib.npyio.NpzFile) -> dict[str, np.ndarray]:
    pol, seek = trials["policy/mroe"], trials["seek/mroe"]
    easy, hard = seek < EASY, seek > HARD
    return {"all": np.ones_like(easy), "easy": easy, "easy_lost": easy & (pol > EASY),
            "easy_kept": easy & (pol <= EASY), "hard": hard}  # fmt: skip


@torch.no_grad()
def replay(
    setup, env, trials
) -> tuple[dict[str, tuple[np.ndarray, np.ndarray]], list[float | None], float, list[tuple[float, float]]]:
    """(total, orientation) return of policy and seek per fall, the goal dependence by step (None once the
    learned deviation has faded out), Σ_j d_j² of the learned deviation averaged over the falls' steps, and
    the mean tilt error [rad] of policy and seek after every step."""
    k, net = len(trials), setup.policy.module.net
    cols = actor_slices(env.spec, env.observes_sensitivity, env.observes_gravity)
    goal = torch.cat([torch.arange(cols[n].start, cols[n].stop) for n in ("goal_root_quat", "goal_joint_pos")])
    other = torch.roll(torch.arange(k), 1)  # each fall's end pose replaced by the previous fall's
    td = env.reset_to(trials.qpos.repeat(2, 1), trials.qvel.repeat(2, 1), trials.pose_ids.repeat(2))
    start_q = env.sim.state.joint_pos.clone()
    total, orientation, dependence, squared, tilt_error = torch.zeros(2 * k), torch.zeros(2 * k), [], [], []
    weight = setup.config.reward.orientation
    # −‖R(θ)ᵀe_z − R(θ̂)ᵀe_z‖², the orientation term's tilt distance, read off the critic observation
    tilt = OrientationPotential(env.spec, 1.0, env.observes_sensitivity, env.observes_gravity)
    for _ in range(env.max_steps):
        obs = td["policy"][:k]
        swapped = obs.clone()
        swapped[:, goal] = obs[other][:, goal]
        deviation = [net.deviation(o) for o in (obs, swapped)]
        size = deviation[0].norm(dim=-1).mean()
        squared.append(deviation[0].square().sum(-1).mean().item())
        dependence.append(((deviation[0] - deviation[1]).norm(dim=-1).mean() / size).item() if size > 0 else None)
        action = torch.empty_like(env.last_action)
        action[:k] = setup.policy(td[:k].select("policy"))["action"]
        action[k:] = seek_action(env, start_q, slice(k, None))
        td = env.step(td.set("action", action))["next"]
        total += td["reward"].view(-1)
        distance = tilt(td["critic"]).view(-1)  # −‖Δ up axis‖², the chord of the up axes' angle
        orientation += weight * env.dt * env.tracking_blend() * distance
        angle = 2.0 * torch.asin((-distance).clamp(min=0.0).sqrt().mul(0.5).clamp(max=1.0))
        tilt_error.append((angle[:k].mean().item(), angle[k:].mean().item()))
    returns = {"policy": (total[:k].numpy(), orientation[:k].numpy()), "seek": (total[k:].numpy(), orientation[k:].numpy())}
    return returns, dependence, float(np.mean(squared)), tilt_error


@torch.no_grad()
def tilt_errors_under_noise(setup, run_config, trials, repeats: int, seed: int) -> dict[str, np.ndarray]:
    """Final orientation error [repeats, k] of the policy's mean and of seek on the `trials` falls, each with
    N(0, σ²) added to every action, σ the policy's trained std per joint (its exploration in training)."""
    k, std = len(trials), setup.policy.module.net.log_std.exp()
    blocks = 2 * repeats  # policy, seek, policy, seek, ...
    env = make_env(run_config, robot_spec(run_config.robot), split=setup.split, seed=setup.config.eval.seed,
                   num_envs=blocks * k, poses=setup.poses)  # fmt: skip
    policy_rows = torch.arange(blocks * k) // k % 2 == 0
    td = env.reset_to(trials.qpos.repeat(blocks, 1), trials.qvel.repeat(blocks, 1), trials.pose_ids.repeat(blocks))
    start_q, g = env.sim.state.joint_pos.clone(), torch.Generator().manual_seed(seed)
    for _ in range(env.max_steps):
        action = seek_action(env, start_q)
        action[policy_rows] = setup.policy(td[policy_rows].select("policy"))["action"]
        action = action + std * torch.randn(action.shape, generator=g)
        td = env.step(td.set("action", action))["next"]
    target = env.end_poses.root_quat[trials.pose_ids.repeat(blocks).to(env.device)]
    error = mroe(env.sim.state.root_quat, target).numpy().reshape(repeats, 2, k)
    return {"policy": error[:, 0], "seek": error[:, 1]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path, help="a training run directory with checkpoints/ and eval_trials.npz")
    ap.add_argument("--noise-repeats", type=int, default=2, help="replays of the falls under the training's noise")
    args = ap.parse_args()
    per_fall = np.load(args.run / "eval_trials.npz")
    if "seek/mroe" not in per_fall.files:
        raise SystemExit(f"{args.run}/eval_trials.npz has no seek rows: evaluate with eval.seek_reference=true")
    trained = validate(yaml.safe_load((args.run / "resolved_config.yaml").read_text()))
    config = trained.model_copy(update={"checkpoint": str(args.run)})
    setup = prepare(config)
    if setup.policy.module.net.prior is None:
        raise SystemExit(f"{args.run}: the policy has no prior, so it has no learned deviation to measure")
    k = len(per_fall["policy/mroe"])
    run_config = eval_run_config(setup.config, config.eval.seconds)
    run_config = run_config.model_copy(update={"reward": setup.config.reward})  # the training reward, on
    env = make_env(run_config, robot_spec(run_config.robot), split=setup.split, seed=config.eval.seed,
                   num_envs=2 * k, poses=setup.poses)  # fmt: skip
    trials = draw_trials(env, k, config.eval.seed)
    returns, dependence, deviation_sq, tilt_error = replay(setup, env, trials)
    groups = fall_groups(per_fall)
    pol = per_fall["policy/mroe"]
    out = {"run": str(args.run), "falls": k, "groups": {g: int(m.sum()) for g, m in groups.items()},
           "easy_kept": float(np.mean(pol[groups["easy"]] <= EASY)),
           "hard_fixed": float(np.mean(pol[groups["hard"]] <= EASY)),
           "seek_keeps_policys": float(np.mean(per_fall["seek/mroe"][pol <= EASY] < EASY)), "returns": {}}  # fmt: skip
    print(f"{args.run}: seek lands {groups['easy'].sum()} of {k} falls within {EASY} rad; the policy keeps "
          f"{out['easy_kept']:.0%} of them and fixes {out['hard_fixed']:.0%} of the {groups['hard'].sum()} beyond {HARD} rad; "
          f"of the {int((pol <= EASY).sum())} it lands within {EASY} rad, seek lands {out['seek_keeps_policys']:.0%}")  # fmt: skip
    print(f"{'falls':10s} {'n':>4s}  return policy / seek   orientation policy / seek   the rest policy / seek")
    for g, m in groups.items():
        row = {s: {"return": float(t[m].mean()), "orientation": float(o[m].mean())} for s, (t, o) in returns.items()}
        out["returns"][g] = row
        p, s = row["policy"], row["seek"]
        print(f"{g:10s} {m.sum():4d}  {p['return']:7.1f} / {s['return']:7.1f}   {p['orientation']:7.1f} / "
              f"{s['orientation']:7.1f}          {p['return'] - p['orientation']:7.1f} / {s['return'] - s['orientation']:7.1f}")  # fmt: skip
    steps = int(round(0.2 / env.dt))
    out["goal_dependence"] = {f"{t * env.dt:.1f}": None if dependence[t] is None else round(dependence[t], 3)
                              for t in range(0, len(dependence), steps)}  # fmt: skip
    print("learned deviation's change with another fall's end pose, relative to its size, by time [s]:",
          ", ".join(f"{t}: {'faded' if v is None else f'{v:.2f}'}" for t, v in out["goal_dependence"].items()))  # fmt: skip
    out["deviation_sq"] = round(deviation_sq, 4)
    print(f"learned deviation's size, Σ_j d_j² averaged over the falls' steps: {deviation_sq:.4f}")
    out["tilt_error_by_time"] = {f"{(t + 1) * env.dt:.1f}": [round(p, 3), round(s, 3)]
                                 for t, (p, s) in enumerate(tilt_error) if t % steps == steps - 1}  # fmt: skip
    print("tilt error to the end pose [rad], policy / seek, by time [s]:",
          ", ".join(f"{t}: {p:.2f} / {s:.2f}" for t, (p, s) in out["tilt_error_by_time"].items()))  # fmt: skip
    if args.noise_repeats > 0:
        noisy = tilt_errors_under_noise(setup, run_config, trials, args.noise_repeats, config.eval.seed)
        easy, hard = groups["easy"], groups["hard"]
        out["under_noise"] = {who: {"easy_kept": round(float(np.mean(e[:, easy] <= EASY)), 3),
                                    "hard_fixed": round(float(np.mean(e[:, hard] <= EASY)), 3)}
                              for who, e in noisy.items()}  # fmt: skip
        print(f"under the training's action noise ({args.noise_repeats} replays): " + "; ".join(
            f"{who} keeps {v['easy_kept']:.0%} of the easy falls, fixes {v['hard_fixed']:.0%} of the hard"
            for who, v in out["under_noise"].items()))  # fmt: skip
    print(json.dumps(out))


if __name__ == "__main__":
    main()
