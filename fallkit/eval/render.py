"""`mode=render`: videos of falls, the policy and the standard strategies side by side.

Each fall runs once per strategy from the same initial state toward the same
end pose (the paired rollout of `fallkit.eval.rollout`), recording the simulator
state; the recording is then drawn with MuJoCo's offscreen renderer, one panel
per strategy, with
- the target end pose as a translucent green ghost where the robot comes to
  rest, turned about the vertical to the robot's final heading (the yaw-free
  goal of the paper), and
- contact forces as MuJoCo's contact-force arrows, recomputed per frame from
  the recorded state and actuator torques.

Headless machines need an OpenGL backend: OSMesa (`apt-get install libosmesa6`,
software, everywhere) or EGL (GPU). fallkit selects OSMesa when no display and
no MUJOCO_GL are set (see fallkit/__init__.py); MUJOCO_GL=egl picks the GPU.
"""

from __future__ import annotations

import logging
import math
import os
from pathlib import Path

import mujoco
import numpy as np
import torch

from fallkit.config import FallkitConfig, RenderConfig
from fallkit.errors import ConfigError, RenderError
from fallkit.eval.choice import choose_end_poses
from fallkit.eval.evaluate import make_eval_env, prepare
from fallkit.eval.rollout import Rollout, draw_trials, rollout
from fallkit.poses.checker import PoseChecker
from fallkit.poses.end_pose_set import EndPoseSet
from fallkit.robots.spec import RobotSpec
from fallkit.rotations import yaw_align
from fallkit.sim.base import Layout

log = logging.getLogger(__name__)

GHOST_RGBA = (0.25, 0.85, 0.35, 0.3)






# ---- drawing a recording -----------------------------------------------------------------


class FallPainter:
    """Draws recorded states of one robot: panels with contact forces and a ghost pose."""

    def __init__(self, spec: RobotSpec, width: int, height: int, force_scale: float = 0.3, distance: float = 2.2):
        self.spec = spec
        self.layout = Layout(spec)
        m = spec.mj_spec()
        m.visual.global_.offwidth = max(width, 640)
        m.visual.global_.offheight = max(height, 480)
        self.model = m.compile()
        # The recorded actuator torques are applied as generalized forces, so the
        # constraint solver sees the forces the simulator had (gains of any strategy).
        self.model.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_ACTUATION
        weight = float(self.model.body_subtreemass[0] * -self.model.opt.gravity[2])  # world subtree: whole robot
        # MuJoCo draws a contact force f as an arrow of f·map.force/meanmass metres, meansize·forcewidth wide
        self.model.vis.map.force = force_scale * self.model.stat.meanmass / max(weight, 1e-6)
        self.model.vis.scale.forcewidth = 0.02 / self.model.stat.meansize
        self.model.vis.rgba.contactforce[:] = (1.0, 0.25, 0.1, 1.0)  # red arrows read as "impact"
        self.model.vis.headlight.ambient[:] = (0.35, 0.35, 0.35)
        self.model.vis.headlight.diffuse[:] = (0.6, 0.6, 0.6)
        self.data = mujoco.MjData(self.model)
        self.ghost = mujoco.MjData(self.model)
        self._ghost_on = False
        self.option = mujoco.MjvOption()
        self.option.flags[mujoco.mjtVisFlag.mjVIS_CONTACTFORCE] = True
        self.camera = mujoco.MjvCamera()
        self.camera.distance = distance
        self.camera.elevation = -22.0
        self.width, self.height = width, height
        try:
            self.renderer = mujoco.Renderer(self.model, height, width)
        except Exception as exc:  # missing GL library or context
            gl = os.environ.get("MUJOCO_GL", "(unset)")
            raise RenderError(
                f"cannot render offscreen with MUJOCO_GL={gl}: {exc}. Install OSMesa "
                "(apt-get install libosmesa6) and set MUJOCO_GL=osmesa, or MUJOCO_GL=egl on a GPU machine"
            ) from None

    def close(self) -> None:
        # explicit: left to the garbage collector at exit, the OSMesa binding prints a traceback
        self.renderer.close()

    def __enter__(self) -> "FallPainter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def set_ghost(self, qpos: np.ndarray | None) -> None:
        self._ghost_on = qpos is not None
        if qpos is not None:
            self.ghost.qpos[:] = qpos
            mujoco.mj_kinematics(self.model, self.ghost)

    def look_at(self, point: np.ndarray, azimuth: float) -> None:
        self.camera.lookat[:] = point
        self.camera.azimuth = azimuth

    def frame(self, qpos: np.ndarray, qvel: np.ndarray, joint_torque: np.ndarray) -> np.ndarray:
        """One panel [H, W, 3] of the robot in the given state."""
        d = self.data
        d.qpos[:] = qpos
        d.qvel[:] = qvel
        d.qfrc_applied[:] = 0.0
        d.qfrc_applied[self.layout.joint_qvel.numpy()] = joint_torque
        mujoco.mj_forward(self.model, d)
        r = self.renderer
        r.update_scene(d, self.camera, self.option)
        if self._ghost_on:
            first = r.scene.ngeom
            mujoco.mjv_addGeoms(
                self.model, self.ghost, mujoco.MjvOption(), mujoco.MjvPerturb(), mujoco.mjtCatBit.mjCAT_DYNAMIC, r.scene
            )
            for i in range(first, r.scene.ngeom):
                r.scene.geoms[i].rgba[:] = GHOST_RGBA
        return r.render()


def ghost_qpos(spec: RobotSpec, target_joint_pos: torch.Tensor, target_quat: torch.Tensor, final_qpos: torch.Tensor) -> np.ndarray:
    """The end pose where the robot ended: at its final xy, turned to its heading, on the ground [k, nq]."""
    checker = PoseChecker(spec)
    r = checker.layout.root_qpos
    quat = yaw_align(target_quat.double(), final_qpos[:, r + 3 : r + 7].double())
    q, _ = checker.on_ground(quat, target_joint_pos, clearance=0.0, root_pos=final_qpos[:, r : r + 3])
    return q.numpy()


def label(image: np.ndarray, lines: list[str]) -> np.ndarray:
    """Write text lines into the top-left corner of an image."""
    from PIL import Image, ImageDraw

    im = Image.fromarray(image)
    draw = ImageDraw.Draw(im)
    for i, text in enumerate(lines):
        draw.text((7, 5 + 13 * i), text, fill=(0, 0, 0))
        draw.text((6, 4 + 13 * i), text, fill=(255, 255, 255))
    return np.asarray(im)


def render_rollout(out: Rollout, spec: RobotSpec, end_poses: EndPoseSet, pose_ids: torch.Tensor, rc: RenderConfig) -> list[np.ndarray]:
    """Frames of every fall of a recorded rollout (`rollout(..., record_states=True)`).

    Per fall, one frame per `render.fps` of simulated time: the strategies' panels
    side by side, each looking across the fall at its own robot.
    """
    strategies = out.strategies
    k = out.qpos.shape[1] // len(strategies)
    stride = frame_stride(spec.policy_hz, rc.fps)
    frames: list[np.ndarray] = []
    with FallPainter(spec, rc.width, rc.height, rc.force_scale, rc.distance) as painter:
        r = painter.layout.root_qpos
        for fall in range(k):
            worlds = [i * k + fall for i in range(len(strategies))]
            pid = pose_ids[fall : fall + 1].cpu()
            ghosts = ghost_qpos(
                spec,
                end_poses.joint_pos.cpu()[pid].expand(len(worlds), -1),
                end_poses.root_quat.cpu()[pid].expand(len(worlds), -1),
                out.qpos[-1, worlds],
            )
            # one viewing direction for all panels: across the mean direction of travel
            xy = out.qpos[:, worlds, r : r + 2].double()  # [T+1, S, 2]
            travel = (xy[-1] - xy[0]).mean(dim=0)
            azimuth = math.degrees(math.atan2(float(travel[1]), float(travel[0]))) + 90.0 if travel.norm() > 0.05 else 135.0
            for t in range(0, out.qpos.shape[0], stride):
                panels = []
                for j, w in enumerate(worlds):
                    centre = xy[:, j].mean(dim=0).numpy()
                    painter.look_at(np.array([centre[0], centre[1], 0.3]), azimuth)
                    painter.set_ghost(ghosts[j])
                    img = painter.frame(out.qpos[t, w].numpy(), out.qvel[t, w].numpy(), out.joint_torque[t, w].numpy())
                    text = [strategies[j].replace("_", " "), f"t = {t * spec.policy_dt:.2f} s"]
                    if k > 1:
                        text.append(f"fall {fall + 1}/{k}")
                    panels.append(label(img, text))
                frames.append(np.concatenate(panels, axis=1))
    return frames


def frame_stride(policy_hz: float, fps: float) -> int:
    """Policy steps per video frame."""
    if fps > policy_hz + 1e-9:
        raise ConfigError(f"render.fps: at most the policy rate ({policy_hz:g} Hz), got {fps:g}")
    return max(1, round(policy_hz / fps))


def write_video(frames: list[np.ndarray], path_stem: Path, fps: float, fmt: str) -> list[Path]:
    """MP4 (H.264 via imageio-ffmpeg) and/or GIF of the frames."""
    import imageio.v3 as iio

    stack = np.stack(frames)
    written = []
    if fmt in ("mp4", "both"):
        p = path_stem.with_suffix(".mp4")
        iio.imwrite(p, stack, fps=fps, codec="libx264", macro_block_size=16)
        written.append(p)
    if fmt in ("gif", "both"):
        p = path_stem.with_suffix(".gif")
        iio.imwrite(p, stack, duration=1000.0 / fps, loop=0)
        written.append(p)
    return written


def run_render(config: FallkitConfig, run_dir: Path) -> list[Path]:
    """`mode=render`: record `render.falls` paired falls and write falls.mp4 / falls.gif."""
    rc = config.render
    ev = config.eval
    torch.set_num_threads(1)  # the physics threads are MuJoCo's (2 torch threads beside them measured 1.5-1.8x slower)
    setup = prepare(config)
    strategies = setup.strategies
    env = make_eval_env(setup, len(strategies) * rc.falls, ev.seconds, ev.seed)
    stride = frame_stride(env.spec.policy_hz, rc.fps)  # a bad render.fps fails before the rollout
    trials = draw_trials(env, rc.falls, ev.seed)
    if setup.choice is not None:  # eval.poses=auto: the ghost is the pose chosen for each fall
        trials = choose_end_poses(env, trials, setup.choice)
    log.info("render %s: %d fall(s) × %s, %.2f s each", env.spec.name, rc.falls, ", ".join(strategies), env.max_steps * env.dt)
    out = rollout(env, trials, strategies, setup.policy, record_states=True)
    frames = render_rollout(out, env.spec, env.end_poses, trials.pose_ids, rc)
    paths = write_video(frames, Path(run_dir) / "falls", env.spec.policy_hz / stride, rc.format)
    for p in paths:
        print(f"video: {p}")
    return paths
