"""FallEnv: the batched falling environment as a TorchRL `EnvBase` (paper Sec. IV-A, IV-B, IV-D, V-A).

One FallEnv drives all N worlds of a `BatchSim` (`batch_size=[N]`, on the
simulator's device). Each episode starts from a random falling state
(`InitialStateSampler`, Table II) with an end pose drawn uniformly from an
`EndPoseSet`, runs for a fixed time T (truncation only: a fall has no failure
state; training may end some at T_blend, `shorten_episodes`) and is then reset
per world through TorchRL's `"_reset"` mask.

Keys (TensorDict):
  "action"         [N, J]  joint setpoint = nominal pose + action_scale · action [rad],
                           clipped to the joint limits; PD at physics rate
  "policy"         [N, Da] actor observation (fallkit.env.observations), noisy; with
                           env.sensitivity_inputs it ends in ln w_c, drawn per episode
  "critic"         [N, Dc] privileged critic observation, noiseless
  "contact_force"  [N, C]  per component, the largest |f_c| over the physics substeps
                           of the step [N]: for metrics, not an input
  "reward"         [N, 1]  policy_dt · Σ_k weight_k · term_k (fallkit.env.rewards)
  "reward_terms"   [N, K]  the reward's K summands (RewardSum.columns order: a term per column, the
                           impact one per component; 0 at a reset): not an input
  "done", "terminated", "truncated" [N, 1]; terminated is always False
  "fall_id"        [N]     training with replay only: the play each step belongs to (`replay_levels`)
Per-term reward means: `env.pop_reward_terms()` / `env.reward_terms_mean`.

Goal (paper Sec. IV-A): the end pose's root orientation with its heading
removed (`tilt_quat`) is the target in the path frame; the world-frame target
at time t is that tilt turned to the robot's current heading, so the policy is
free to fall in any direction and the orientation reward compares tilt only.
"""

from __future__ import annotations

import logging
import math

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from fallkit import registry
from fallkit.config import EnvConfig, LevelReplayConfig, RewardConfig
from fallkit.env.checks import check_inputs, check_reset_to
from fallkit.env.observations import (
    actor_layout,
    actor_observation,
    critic_layout,
    critic_observation,
    noise_std,
    path_frame,
    planar_motion,
)
from fallkit.env.randomization import EpisodeRandomization, SensitivityDraw
from fallkit.env.rewards.context import RewardContext, RewardSum
from fallkit.env.rewards.tracking import blend
from fallkit.env.run_state import load_run_state, save_run_state
from fallkit.env.samplers.end_pose import EndPoseDraw
from fallkit.env.samplers.initial_state import InitialStateStock
from fallkit.env.samplers.replay import LevelReplay
from fallkit.poses.end_pose_set import EndPoseSet
from fallkit.robots.spec import RobotSpec
from fallkit.rotations import tilt_quat
from fallkit.sim.base import BatchSim

log = logging.getLogger(__name__)

__all__ = ["FallEnv"]


class FallEnv(EnvBase):
    """Soft, goal-directed falling of N worlds (see the module docstring)."""

    def __init__(
        self,
        spec: RobotSpec,
        env_cfg: EnvConfig,
        reward_cfg: RewardConfig,
        end_poses: EndPoseSet,
        sim: BatchSim,
        seed: int = 0,
    ):
        n = sim.num_worlds
        super().__init__(device=sim.device, batch_size=[n])
        check_inputs(spec, env_cfg, reward_cfg, end_poses, sim)
        self.spec = spec
        self.env_cfg = env_cfg
        self.reward_cfg = reward_cfg
        self.sim = sim
        self.end_poses = end_poses.to(self.device)
        self.num_envs = n
        self.dt = spec.policy_dt
        self.max_steps = max(1, round(env_cfg.episode_length / self.dt))
        self.action_scale = env_cfg.action_scale
        self.observes_sensitivity = env_cfg.sensitivity_inputs.enabled
        self.observes_gravity = env_cfg.observe_gravity

        # seeded generators owned by the env: CPU for the MuJoCo-based initial-state
        # sampler, the sim's device for everything drawn per step
        self._cpu_gen = torch.Generator()
        self._gen = torch.Generator(device=self.device)
        self._set_seed(seed)
        self._make_samplers_and_rewards()
        self._make_constants()
        self._make_episode_buffers()
        self.randomization = EpisodeRandomization(env_cfg.randomization, sim, spec.friction, self.device)
        self.level_replay: LevelReplay | None = None  # training only: replay_levels
        self._make_specs()

    # ---- public helpers -------------------------------------------------------------

    def action_for_setpoint(self, q: torch.Tensor) -> torch.Tensor:
        """The action whose setpoint is q [.., J] (inverse of the action mapping)."""
        return (q.to(self.nominal) - self.nominal) / self.action_scale

    def setpoint(self, action: torch.Tensor) -> torch.Tensor:
        """Joint setpoints [N, J] of an action: nominal + action_scale · a, clipped to the limits."""
        q = torch.add(self.nominal, action, alpha=self.action_scale)  # no per-step constant tensor (a copy to a GPU)
        if self.env_cfg.clip_setpoints:
            q = torch.minimum(torch.maximum(q, self._q_lo), self._q_hi)
        return q

    def reset_to(self, qpos: torch.Tensor, qvel: torch.Tensor, end_pose_ids: torch.Tensor) -> TensorDictBase:
        """Reset ALL worlds to given MuJoCo-layout states and end poses (paired evaluation)."""
        n, ids = self.num_envs, end_pose_ids.to(self.device, torch.long)
        check_reset_to(n, qpos, qvel, ids, len(self.end_poses))
        self._reset_worlds(self._all, torch.arange(n, device=self.device), qpos, qvel, ids)
        return self._observation(self._no.expand(n, 1))

    def target_root_quat(self) -> torch.Tensor:
        """The current world-frame target θ̂_t [N, 4]: the end pose's tilt turned to the robot's heading."""
        return path_frame(self.sim.state.root_quat).turn(self.goal_root_quat)

    def end_pose_goals(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Every end pose of this env's set as a goal is observed: its tilt in the path frame [P, 4] and its
        joint angles [P, J], float32 (what `reset` puts into goal_root_quat and goal_joint_pos)."""
        return self._goal_tilt, self.end_poses.joint_pos.to(torch.float32)

    def episode_starts(self) -> torch.Tensor:
        """[N] bool: the worlds whose next action is the first of their episode."""
        return self.step_count == 0

    def tracking_blend(self) -> torch.Tensor:
        """u(t) [N] of every world at its current step: 0 when the fall begins, 1 after T_blend."""
        return blend(self.step_count * self.dt, self.reward_cfg.blend_time)

    @property
    def reward_terms_mean(self) -> dict[str, torch.Tensor]:
        """Per-term mean over worlds of the last step's contribution (weight · term · dt), 0-dim tensors."""
        return dict(zip(self.rewards.names, self.rewards.last_mean.unbind()))

    def pop_reward_terms(self) -> dict[str, float]:
        """Per-term mean contribution per step since the last call (weight · term · dt); then starts over."""
        return self.rewards.pop_means()

    def stagger_episodes(self) -> None:
        """Training only: spread the worlds' episode clocks over their episodes. Else all start together, every
        impact of the batch falls in the same iterations, and PPO's adaptive learning rate swings with T."""
        step = torch.randint(self.max_steps, (self.num_envs,), generator=self._gen, device=self.device)
        self.step_count.copy_(step.remainder_(self.episode_steps))  # within each world's own episode

    def shorten_episodes(self, fraction: float) -> None:
        """Training only: end this fraction of the episodes (drawn per episode) at T_blend instead of T,
        truncated: the critic's value, learned from the episodes that run to T, stands in for the rest."""
        self._short = (fraction, min(self.max_steps, math.ceil(self.reward_cfg.blend_time / self.dt - 1e-6)))

    def replay_levels(self, config: LevelReplayConfig) -> LevelReplay:
        """Training only: a share of the restarts replay stored falls chosen by score (fallkit.env.samplers.replay);
        every step then carries its play's "fall_id" [N], for the trainer's `LevelReplay.record`."""
        nq, nv = self.sim.state.qpos.shape[1], self.sim.state.qvel.shape[1]
        self.level_replay = LevelReplay(config, self.num_envs, nq, nv, self.device)
        self._make_specs()  # with "fall_id"
        return self.level_replay

    def run_state(self) -> dict:
        """Everything needed to continue exactly (fallkit.env.run_state)."""
        return save_run_state(self)

    def load_run_state(self, state: dict) -> None:
        """Restore what run_state() returned (same robot, number of envs and config)."""
        load_run_state(self, state)

    @property
    def num_unstable(self) -> int:
        """Worlds found unstable so far (their episodes were truncated and reset)."""
        return self.sim.num_unstable

    # ---- EnvBase ----------------------------------------------------------------------

    def _set_seed(self, seed: int | None) -> None:
        seed = 0 if seed is None else int(seed)
        self._cpu_gen.manual_seed(seed)
        self._gen.manual_seed(seed + 1)

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        mask = tensordict.get("_reset", None) if tensordict is not None else None
        mask = self._all if mask is None else mask.view(-1).to(self.device)
        self._restart(mask, mask.nonzero().view(-1))
        return self._observation(self._no.expand(self.num_envs, 1))

    def step_and_maybe_reset(self, tensordict: TensorDictBase) -> tuple[TensorDictBase, TensorDictBase]:
        """TorchRL's, for FallEnv's one done key, with one host read per step instead of ~6 (TorchRL asks
        `done.any()` and checks the reset's done flags): the restarting worlds' ids, which the host's
        initial-state sampler needs anyway. The same tensors to the bit (tested against TorchRL's)."""
        td = self.step(tensordict if tensordict.device == self.device else tensordict.to(self.device))
        nxt = self._step_mdp(td)
        done = nxt.get("done").view(-1)
        if self._restart(done, done.nonzero().view(-1)):
            fresh = self._observation(self._no.expand(self.num_envs, 1))
            nxt.where(~done, other=fresh, out=nxt, pad=0, update_batch_size=True)  # TorchRL's own merge
        return td, nxt

    def _restart(self, mask: torch.Tensor, ids: torch.Tensor) -> bool:
        """A fresh initial state and end pose for worlds `ids` (where `mask` [N] is true); False if none."""
        if not ids.numel():
            return False
        qpos, qvel = self.initial_stock.take(ids.numel(), self._cpu_gen)
        poses = self.end_pose_draw(qpos, qvel, self._gen)
        if self.level_replay is not None:
            qpos, qvel, poses = self.level_replay.restart(ids, qpos, qvel, poses, self._cpu_gen)
        self._reset_worlds(mask, ids, qpos, qvel, poses)
        return True

    def _reset_worlds(
        self, mask: torch.Tensor, ids: torch.Tensor, qpos: torch.Tensor, qvel: torch.Tensor, poses: torch.Tensor
    ) -> None:
        self.sim.reset(ids, qpos, qvel)
        st = self.sim.state
        ids = ids.to(self.device)
        self.step_count[ids] = 0
        fraction, short = self._short
        if fraction > 0:  # drawn only then: a run without short episodes draws the numbers it drew before
            cut = torch.rand(len(ids), generator=self._gen, device=self.device) < fraction
            self.episode_steps[ids] = torch.where(cut, short, self.max_steps)
        self.end_pose_ids[ids] = poses
        self.goal_root_quat[ids] = self._goal_tilt[poses]
        self.goal_joint_pos[ids] = self.end_poses.joint_pos[poses].to(torch.float32)
        hold = self.action_for_setpoint(st.joint_pos[ids])  # the sim holds the reset pose
        self.last_action[ids] = hold
        self.last_last_action[ids] = hold
        self._motion[ids] = torch.cat((planar_motion(st.body_vel[ids, 1:]), torch.zeros_like(self._motion[ids, 2:])), 1)
        self._reward_terms = self._reward_terms.index_fill(0, ids, 0.0)  # not in place: the last step's output holds it
        if self.disturbances is not None:
            self.disturbances.reset(mask, self._gen)
        self.randomization.reset(ids, self._gen)
        drawn = self.draw_sensitivity(len(ids), self._gen)
        if drawn is not None:
            self.sensitivity[ids] = drawn

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get("action")
        if self.disturbances is not None:
            self.sim.set_external_wrench(self.disturbances.body_ids, self.disturbances.step(self.dt, self._gen))
        st = self.sim.step(self.setpoint(self.randomization.applied(action, self.last_action)))
        self.step_count += 1
        unstable = st.unstable.to(self.device)

        vel = planar_motion(st.body_vel[:, 1:])
        acc = torch.sub(vel, self._motion[:, :2]).mul_(1.0 / self.dt)
        # unstable worlds were put back to their reset state by the sim: no acceleration
        acc.masked_fill_(unstable.view(-1, 1, 1, 1), 0.0)
        self._motion = torch.cat((vel, acc), dim=1)

        frame = path_frame(st.root_quat)
        t = self.step_count * self.dt
        u = blend(t, self.reward_cfg.blend_time)  # once per step: the reward's and the actor's u(t)
        ctx = RewardContext(
            state=st, action=action, last_action=self.last_action, last_last_action=self.last_last_action,
            target_root_quat=frame.turn(self.goal_root_quat), target_joint_pos=self.goal_joint_pos,
            sensitivity=self.sensitivity, time=t, blend=u, force_unit=self.reward_cfg.force_unit,
            force_clip=self.reward_cfg.force_clip, dt=self.dt,
        )  # fmt: skip
        self._reward_terms = self.rewards.contributions(ctx).masked_fill_(unstable.view(-1, 1), 0.0)
        self.last_last_action = self.last_action
        self.last_action = action.clone()
        truncated = ((self.step_count >= self.episode_steps) | unstable).view(-1, 1)
        out = self._observation(truncated, frame, u)
        out.set("reward", self._reward_terms.sum(dim=1, keepdim=True))
        return out

    # ---- construction -------------------------------------------------------------

    def _make_samplers_and_rewards(self) -> None:
        """The registered initial-state sampler, the disturbances (if enabled and the robot
        names bodies to push), the reward terms and the training episodes' end-pose draw."""
        spec, env_cfg, load = self.spec, self.env_cfg, registry.load
        self.initial_states = load("fallkit.samplers", env_cfg.samplers["initial_state"])(
            spec, **env_cfg.initial_state.model_dump()
        )
        # training's restarts take a few states per step: drawn ahead, a quarter of the worlds at a time
        self.initial_stock = InitialStateStock(self.initial_states, chunk=max(64, self.num_envs // 4))
        dist, self.disturbances = env_cfg.disturbances, None
        if dist.enabled:
            self.disturbances = load("fallkit.samplers", env_cfg.samplers["disturbances"])(
                spec, self.num_envs, self.device, **dist.model_dump(exclude={"enabled"})
            )
            if self.disturbances.body_ids.numel() == 0:  # the robot names none of the roles
                self.disturbances = None
        self.rewards = RewardSum(self.reward_cfg, self.dt, self.device, components=spec.component_names)
        draw = env_cfg.heading_end_poses, env_cfg.heading_candidates
        self.end_pose_draw = EndPoseDraw(self.end_poses.root_quat, self.sim.layout, *draw)

    def _make_constants(self) -> None:
        """Robot and goal constants on the device: nominal pose, joint limits, sensitivity,
        the end poses' tilts, and the observation noise."""
        spec, f32 = self.spec, dict(dtype=torch.float32, device=self.device)
        self.nominal = torch.as_tensor(spec.nominal_q(), **f32)
        limits = torch.as_tensor(spec.joint_limits, **f32)
        self._q_lo, self._q_hi = limits[:, 0], limits[:, 1]
        self.draw_sensitivity = SensitivityDraw(self.env_cfg.sensitivity_inputs, spec, self.device)  # .weights: [C]
        self._goal_tilt = tilt_quat(self.end_poses.root_quat.to(torch.float32))  # [P, 4]
        std = noise_std(spec, self.env_cfg.noise, self.observes_sensitivity, self.observes_gravity)
        noisy = std.nonzero()
        # noise is drawn up to the last measured column (std 0 on exact parts before it, e.g. the goal)
        self._noise_cols = int(noisy.max()) + 1 if len(noisy) else 0
        self._noise_std = std[: self._noise_cols].to(self.device)

    def _make_episode_buffers(self) -> None:
        """Per-world episode state: clock, goal, the last two actions, body motion."""
        n, dev, f32 = self.num_envs, self.device, dict(dtype=torch.float32, device=self.device)
        j, nb = len(self.spec.joints), self.sim.state.body_vel.shape[1] - 1
        self.step_count = torch.zeros(n, dtype=torch.long, device=dev)
        self.episode_steps = torch.full((n,), self.max_steps, dtype=torch.long, device=dev)  # T, or shorter
        self._short = (0.0, self.max_steps)  # the fraction of episodes that end early, and when (shorten_episodes)
        self.end_pose_ids = torch.zeros(n, dtype=torch.long, device=dev)
        self.goal_root_quat = torch.zeros(n, 4, **f32)  # path frame
        self.goal_joint_pos = torch.zeros(n, j, **f32)
        self.last_action = torch.zeros(n, j, **f32)
        self.last_last_action = torch.zeros(n, j, **f32)
        self._motion = torch.zeros(n, 4, 3, nb, **f32)  # body velocity, acceleration (planar_motion layout)
        self._reward_terms = torch.zeros(n, len(self.rewards.columns), **f32)
        # [N, C] w_c of every world: the robot's, or drawn per episode with env.sensitivity_inputs
        self.sensitivity = self.draw_sensitivity.weights.expand(n, -1).clone()
        self._all = torch.ones(n, dtype=torch.bool, device=dev)
        self._no = torch.zeros(n, 1, dtype=torch.bool, device=dev)

    def _make_specs(self) -> None:
        """TorchRL's observation, action, reward and done specs (see the module docstring)."""
        n, dev, spec = self.num_envs, self.device, self.spec
        options = (self.observes_sensitivity, self.observes_gravity)
        da = sum(s for _, s in actor_layout(spec, *options))
        dc = sum(s for _, s in critic_layout(spec, *options))
        self.observation_spec = Composite(
            policy=Unbounded((n, da), device=dev),
            critic=Unbounded((n, dc), device=dev),
            contact_force=Unbounded((n, len(spec.components)), device=dev),
            reward_terms=Unbounded((n, len(self.rewards.columns)), device=dev),
            **({"fall_id": Unbounded((n,), dtype=torch.long, device=dev)} if self.level_replay is not None else {}),
            shape=(n,),
            device=dev,
        )
        self.action_spec = Unbounded((n, len(spec.joints)), device=dev)
        self.reward_spec = Unbounded((n, 1), device=dev)
        flag = lambda: Categorical(2, (n, 1), dtype=torch.bool, device=dev)  # noqa: E731
        self.done_spec = Composite(done=flag(), terminated=flag(), truncated=flag(), shape=(n,), device=dev)

    # ---- internals ----------------------------------------------------------------

    def _observation(self, truncated: torch.Tensor, frame=None, u: torch.Tensor | None = None) -> TensorDictBase:
        st = self.sim.state
        frame = frame if frame is not None else path_frame(st.root_quat)
        u = u if u is not None else self.tracking_blend()
        observed = u if self.env_cfg.observe_blend else torch.zeros_like(u)  # the paper's actor has no clock
        actor = actor_observation(
            frame, st.root_quat, st.root_lin_vel, st.root_ang_vel, st.joint_pos, st.joint_vel,
            self.last_action, self.last_last_action, self.goal_root_quat, self.goal_joint_pos, observed,
            self.sensitivity if self.observes_sensitivity else None, self.observes_gravity,
        )  # fmt: skip
        critic = critic_observation(
            actor, frame, self.step_count * (1.0 / self.max_steps), self.randomization.friction, st.root_pos[:, 2],
            st.body_pos[:, 1:, 2], self._motion,
        )  # fmt: skip
        policy = actor
        if self._noise_cols:
            k = self._noise_cols
            policy = actor.clone()
            noise = torch.randn((actor.shape[0], k), generator=self._gen, device=self.device)
            policy[:, :k].addcmul_(noise, self._noise_std)
        keys = dict(
            policy=policy, critic=critic, contact_force=st.peak_contact_force(), reward_terms=self._reward_terms,
            done=truncated.clone(), terminated=torch.zeros_like(truncated), truncated=truncated,
        )  # fmt: skip
        if self.level_replay is not None:
            keys["fall_id"] = self.level_replay.fall_id.clone()
        return TensorDict(keys, batch_size=self.batch_size, device=self.device)

