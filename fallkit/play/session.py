"""The simulation side of mode=play: falls run by mode=eval's own code, watched step by step.

A `PlaySession` owns one evaluation env (`fallkit.eval.evaluate.make_eval_env`: no observation
noise, no disturbances, the run's robot and observations) with one world per strategy shown, and
runs every fall with `fallkit.eval.rollout.rollout`, the paired rollout of mode=eval, watching it
through its `on_step` hook. The metrics of a fall are `fallkit.eval.metrics.trial_metrics` of that
rollout's traces: for the same initial state and end pose they are exactly what mode=eval
computes (tests/test_play.py checks it through the browser). Nothing here draws: every step
becomes a `Frame` handed to a callback (fallkit.play.scene draws it, fallkit.play.server paces it).

With `eval.poses=auto` the page can leave the end pose to the fall: chosen from the poses shown
(restricted by `eval.candidate_side`) by `eval.scorer` at the fall's first state, as mode=eval and
mode=render choose it (`fallkit.eval.choice.choose_end_poses`).

Two ways a fall starts:
- random: the initial state of `draw_trials(env, 1, seed)` (paper Table II through the run's
  registered sampler), i.e. the first fall of `mode=eval eval.seed=<seed>`;
- push: the robot stands in its nominal pose, holding it with the nominal gains, and an impulse
  (N·s, horizontal, on the root body) acts over `play.push_time`; the state after it is the
  initial state of the fall, from which every strategy takes over.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import torch

from fallkit.config import FallkitConfig, validate
from fallkit.errors import ConfigError, PoseFileError
from fallkit.eval.choice import PoseChoice, choose_end_poses
from fallkit.eval.evaluate import EvalSetup, make_eval_env, prepare
from fallkit.eval.metrics import TrialMetrics, trial_metrics
from fallkit.eval.rollout import POLICY, SEEK, Trials, draw_trials, rollout
from fallkit.eval.strategies import STRATEGIES
from fallkit.poses.artist import artist_file
from fallkit.poses.checker import PoseChecker
from fallkit.rl.checkpoint import load_checkpoint
from fallkit.robots import robot_spec
from fallkit.sim.base import Layout, SimState

KNOWN = (POLICY, *STRATEGIES, SEEK)


@dataclass(frozen=True)
class FallStart:
    """How a fall begins: its end pose and either a seed (random state) or a push."""

    pose_id: int
    seed: int | None = None  # random initial state: draw_trials(env, 1, seed)
    push: float | None = None  # [N·s] impulse on the standing robot's root body
    direction: float = 0.0  # [deg] of the push: 0 = the robot's front (+x), 90 = its left (+y)
    choose: bool = False  # eval.poses=auto: the end pose chosen for the fall at its first state (pose_id unused)

    def describe(self) -> str:
        if self.push is not None:
            return f"push {self.push:g} N·s toward {self.direction:g}°"
        return f"random initial state, seed {self.seed}"


@dataclass
class Frame:
    """What the browser draws of one moment: every world's state and contact forces."""

    time: float  # [s] since the fall began (negative while a push acts)
    qpos: np.ndarray  # [W, nq] float64, MuJoCo layout
    force: np.ndarray  # [W, C, 3] net contact force per component at the step's last substep [N]
    peak: np.ndarray  # [W, C] largest |f_c| of this fall so far (the metrics' max impact, per component) [N]
    push: np.ndarray | None = None  # [3] force the push applies now [N], None when none


@dataclass
class FallResult:
    """A finished fall: how it began, every strategy's metrics and the frames for replays."""

    number: int
    start: FallStart
    pose_id: int  # the end pose the fall steered toward: start.pose_id, or the one chosen for it
    metrics: dict[str, TrialMetrics]  # one trial each, as mode=eval's per-trial figures
    frames: list[Frame] = field(default_factory=list)


class PlaySession:
    """The env, the policy and the end poses of one mode=play run (see the module docstring)."""

    def __init__(self, config: FallkitConfig, robot_named: bool = False):
        self.config = session_config(config, robot_named)
        self.setup = prepare(self.config)
        self.setup.poses = pose_source(config.play.poses, self.setup)
        self.strategies = choose_strategies(config.play.strategies, self.setup.policy is not None)
        ev = self.config.eval
        self.env = make_eval_env(self.setup, len(self.strategies), ev.seconds, ev.seed)
        self.spec = self.env.spec
        self.layout = Layout(self.spec)
        self.poses = self.env.end_poses
        self.source = self.setup.poses
        model = self.spec.mj_model()
        self.weight = float(model.body_subtreemass[0] * -model.opt.gravity[2])  # world subtree: the whole robot
        self._checker = PoseChecker(self.spec, chunk=1, threads=1)
        self.falls = 0

    # ---- end poses ---------------------------------------------------------------------

    @property
    def choice(self) -> PoseChoice | None:
        """How a fall's end pose is chosen with eval.poses=auto (None: only by hand in the page)."""
        return self.setup.choice

    def pose_label(self, i: int) -> str:
        return self.poses.names[i] if self.poses.names else f"#{i}"

    def pose_id(self, value: str | int | None, key: str = "play.pose") -> int:
        """The index of a pose given by name or index; an unknown one is a ConfigError naming the choices."""
        n, names = len(self.poses), self.poses.names
        if value is None:
            return 0
        if isinstance(value, int) or (isinstance(value, str) and value.strip().lstrip("-").isdigit()):
            i = int(value)
            if not 0 <= i < n:
                raise ConfigError(f"{key}: pose index {i} is out of range: {self.source} has poses 0..{n - 1}")
            return i
        if value in names:
            return names.index(value)
        listed = ", ".join(names[:12]) + (" …" if len(names) > 12 else "")
        choices = f"poses: {listed}" if names else f"its poses have no names: give an index 0..{n - 1}"
        raise ConfigError(f"{key}: no end pose '{value}' in {self.source}; {choices}")

    def ghost_qpos(self, pose_id: int) -> np.ndarray:
        """The end pose [nq] lying on the ground at the origin, in its settled root orientation."""
        quat = self.poses.root_quat[pose_id : pose_id + 1].cpu()
        joints = self.poses.joint_pos[pose_id : pose_id + 1].cpu()
        return self._checker.on_ground(quat, joints, clearance=0.0)[0][0].numpy()

    def standing_qpos(self) -> torch.Tensor:
        """The nominal pose [1, nq] standing on the floor at the origin, facing +x."""
        quat = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=torch.float64)
        joints = torch.as_tensor(self.spec.nominal_q(), dtype=torch.float64)[None]
        return self._checker.on_ground(quat, joints, clearance=0.0)[0]

    # ---- falls -------------------------------------------------------------------------

    def run(self, start: FallStart, on_frame: Callable[[Frame], None],
            on_pose: Callable[[int], None] | None = None) -> FallResult:  # fmt: skip
        """One paired fall of every strategy from `start`; every step goes to `on_frame` as it happens, and
        the end pose it steers toward to `on_pose` once known (after the push; chosen with start.choose).

        An exception raised by on_frame (a newer request in the browser) ends the fall there.
        """
        self.pose_id(start.pose_id, "pose")  # range check
        if start.choose and self.choice is None:
            raise ConfigError("choosing the end pose for the fall needs eval.poses=auto on the command line "
                              "(eval.scorer=heading, or critic with a checkpoint)")  # fmt: skip
        frames: list[Frame] = []

        def emit(frame: Frame) -> None:
            frames.append(frame)
            on_frame(frame)

        trials = self.push_trials(start, emit) if start.push is not None else self.random_trials(start)
        if start.choose:
            trials = choose_end_poses(self.env, trials, self.choice)
        pose_id = int(trials.pose_ids[0])
        if on_pose is not None:
            on_pose(pose_id)
        env, w, c = self.env, self.env.num_envs, len(self.spec.components)
        peak = torch.zeros(w, c)
        emit(Frame(0.0, trials.qpos.expand(w, -1).numpy().copy(), np.zeros((w, c, 3)), peak.numpy().copy()))

        def on_step(t: int, state: SimState) -> None:
            nonlocal peak
            peak = torch.maximum(peak, state.peak_contact_force().cpu())
            force = state.contact_force[:, -1].cpu().double().numpy()
            emit(Frame((t + 1) * env.dt, state.qpos.cpu().double().numpy(), force, peak.double().numpy()))

        out = rollout(env, trials, self.strategies, self.setup.policy, on_step=on_step)
        self.falls += 1
        metrics = {s: trial_metrics(out.traces[s], env.dt) for s in self.strategies}
        return FallResult(self.falls, start, pose_id, metrics, frames)

    def random_trials(self, start: FallStart) -> Trials:
        """The initial state mode=eval draws first from seed `start.seed`, toward the chosen pose."""
        trials = draw_trials(self.env, 1, int(start.seed or 0))
        return Trials(trials.qpos, trials.qvel, torch.tensor([start.pose_id]))

    def push_trials(self, start: FallStart, emit: Callable[[Frame], None] | None = None) -> Trials:
        """The state after a push on the standing robot (every world alike, nominal gains).

        The impulse acts as a constant force at the root body's centre of mass over whole policy
        steps (force = impulse / their duration, so the impulse is exact); `emit` sees each step.
        """
        env, n = self.env, self.env.num_envs
        steps = max(1, round(self.config.play.push_time / env.dt))
        size = float(start.push or 0.0) / (steps * env.dt)
        angle = math.radians(start.direction)
        push = np.array([size * math.cos(angle), size * math.sin(angle), 0.0])
        env.sim.reset(torch.arange(n), self.standing_qpos().expand(n, -1), torch.zeros(n, self.layout.nv, dtype=torch.float64))
        env.sim.set_gain_scale(torch.ones(n, device=env.device))
        root = torch.tensor([self.layout.root_body])
        wrench = torch.zeros(n, 1, 6, device=env.device)
        wrench[:, 0, :3] = torch.as_tensor(push, dtype=torch.float32, device=env.device)
        env.sim.set_external_wrench(root, wrench)
        targets = env.nominal.expand(n, -1)
        c = len(self.spec.components)
        try:
            for i in range(steps):
                st = env.sim.step(targets)
                if emit is not None:
                    force = st.contact_force[:, -1].cpu().double().numpy()
                    emit(Frame((i + 1 - steps) * env.dt, st.qpos.cpu().double().numpy(), force, np.zeros((n, c)), push))
        finally:  # the fall itself is not pushed, nor the next one when this push is cut short
            env.sim.set_external_wrench(root, torch.zeros_like(wrench))
        st = env.sim.state
        return Trials(st.qpos[:1].cpu().double(), st.qvel[:1].cpu().double(), torch.tensor([start.pose_id]))

    # ---- sensitivity inputs ----------------------------------------------------------------

    def observes_sensitivity(self) -> bool:
        """Whether the policy takes the components' sensitivity weights as inputs (env.sensitivity_inputs;
        the page then shows sliders for them)."""
        return self.setup.policy is not None and self.setup.config.env.sensitivity_inputs.enabled

    def set_sensitivity(self, component: str, weight: float) -> None:
        """Change one component's sensitivity weight in every world (what the policy observes from its next step)."""
        self.env.sensitivity[:, self.spec.component_names.index(component)] = weight


def session_config(config: FallkitConfig, robot_named: bool = False) -> FallkitConfig:
    """The config play's env is built from: the checkpoint's robot (a robot named on the command line
    that differs is a ConfigError; its sensitivity weights count where the policy observes them, see
    fallkit.eval.evaluate.prepare), and one MuJoCo thread unless `sim.threads` says otherwise (a few
    worlds gain nothing from a thread pool)."""
    if config.checkpoint is not None:
        trained = validate(load_checkpoint(config.checkpoint)["config"]).robot
        if trained.name != config.robot.name and robot_named:
            raise ConfigError(
                f"checkpoint={config.checkpoint} is a policy for robot '{trained.name}', not robot={config.robot.name}: "
                f"drop robot= to play it, or choose a checkpoint trained on {config.robot.name}"
            )
        if trained.name != config.robot.name:
            config = config.model_copy(update={"robot": trained})
    return config.model_copy(update={"sim": config.sim.model_copy(update={"threads": config.sim.threads or 1})})


def pose_source(requested: str | None, setup: EvalSetup) -> str:
    """play.poses, else the robot's artist poses (they have names) when it ships them, else mode=eval's."""
    if requested is not None:
        return requested
    try:
        artist_file(robot_spec(setup.config.robot))
    except PoseFileError:
        return setup.poses
    return "artist"


def choose_strategies(requested: list[str] | None, have_policy: bool) -> list[str]:
    """play.strategies checked: known names, no repeats, the policy only with a checkpoint."""
    if requested is None:
        return ([POLICY] if have_policy else []) + list(STRATEGIES)
    unknown = [s for s in requested if s not in KNOWN]
    if unknown:
        raise ConfigError(f"play.strategies: unknown {unknown}; choose from {', '.join(KNOWN)}")
    if len(set(requested)) != len(requested) or not requested:
        raise ConfigError(f"play.strategies: name each strategy once, at least one (got {requested})")
    if POLICY in requested and not have_policy:
        raise ConfigError("play.strategies: 'policy' needs a trained policy: add checkpoint=<run dir>")
    return list(requested)
