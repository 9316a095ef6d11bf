"""FallController: the exported policy beside a robot's own controller, at the policy rate.

    controller = FallController.load("runs/train/biped20/<time>/export")
    controller.reset("prone_shield_head")          # or EndPose(joints=..., ground="back"),
                                                   # or controller.choose_end_pose(state): the one the fall heads for
    every 20 ms:  command = controller.step(state)  # RobotState from the robot's estimator
                  apply command.setpoint with command.kp, command.kd, command.torque_limit

It rebuilds the actor observation exactly as the training environment does (the path
frame, the heading-free goal tilt, the action history, the tracking blend u(t); the
layout is read from policy.json and checked against the one built here), runs the
ONNX network and turns its action into joint setpoints. A missing or late estimate
is `step(None)`: the controller then holds its last setpoints or damps the joints
(`on_missing`), and counts it. Imports numpy and onnxruntime only, so it runs on a
robot's computer. docs/deploy.md documents frames, units and a control loop.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Mapping, Sequence

import numpy as np

from fallkit.deploy.state import EndPose, RobotState, check_state, read_policy_json
from fallkit.errors import DeployError
from fallkit.pose_choice import PIVOT_HEIGHT, SIDES, choose_by_heading, side_counts, side_rows
from fallkit.pose_format import gravity_in_frame

_META_KEYS = ("robot", "joint_names", "policy_hz", "action_scale", "nominal_pose", "joint_limits", "pd_gains",
              "observation_size", "observation_layout", "tracking_blend")  # fmt: skip
log = logging.getLogger(__name__)

_LAYOUT = ("root_quat", "root_lin_vel", "root_ang_vel", "joint_pos", "joint_vel", "last_action", "last_last_action",
           "goal_root_quat", "goal_joint_pos", "blend")  # fmt: skip


@dataclass
class Command:
    """What to apply until the next step, per joint in the controller's joint order. The same arrays
    are refilled every step (no allocation): copy them to keep one."""

    setpoint: np.ndarray  # [J] joint position setpoints [rad]
    kp: np.ndarray  # [J] PD stiffness [N·m/rad]; 0 while damping
    kd: np.ndarray  # [J] PD damping [N·m·s/rad]
    torque_limit: np.ndarray  # [J] |tau| <= this [N·m]
    source: str = "policy"  # "policy" | "hold" (last setpoints, estimate missing) | "damp" (kp = 0)


class FallController:
    """The exported policy as a 50 Hz controller (see module docstring)."""

    def __init__(self, meta: dict, onnx_path: Path, end_poses: dict[str, EndPose], joint_order: Sequence[str] | None,
                 on_missing: Literal["hold", "damp"]):  # fmt: skip
        import onnxruntime

        self.meta = meta
        self.joint_names: list[str] = list(meta["joint_names"])
        self.joint_order = list(joint_order) if joint_order is not None else list(self.joint_names)
        _check_joint_order(self.joint_order, self.joint_names)
        if on_missing not in ("hold", "damp"):
            raise DeployError(f"on_missing must be 'hold' or 'damp', got {on_missing!r}")
        self.on_missing = on_missing
        self.end_poses = end_poses
        j = len(self.joint_names)
        self.dt = 1.0 / float(meta["policy_hz"])
        self.action_scale = float(meta["action_scale"])
        self.nominal = np.array([meta["nominal_pose"][n] for n in self.joint_names])
        self.limits = np.array([meta["joint_limits"][n] for n in self.joint_names])
        self.clip = bool(meta.get("clip_setpoints", True))
        blend = meta["tracking_blend"]
        self.blend_time, self.observe_blend = float(blend["blend_time"]), bool(blend["observed"])
        self.slices = _check_layout(meta, j)
        # policies trained with env.sensitivity_inputs take the components' weights as inputs (defaults: training's)
        self.sensitivity: dict[str, float] = dict(meta["sensitivity"]["defaults"]) if "sensitivity" in meta else {}
        self._sensitivity_input = np.zeros(len(self.sensitivity), dtype=np.float32)
        self._min_sensitivity = 1e-3  # fallkit.env.observations.MIN_SENSITIVITY (policy.json's formula names it)
        if self.sensitivity:
            self.set_sensitivity(self.sensitivity)
        # robot order <-> policy order
        self.to_policy = np.array([self.joint_order.index(n) for n in self.joint_names])
        self.to_robot = np.array([self.joint_names.index(n) for n in self.joint_order])
        gains = meta["pd_gains"]
        self.command = Command(
            setpoint=np.zeros(j),
            kp=np.array([gains[n]["kp"] for n in self.joint_order], dtype=np.float64),
            kd=np.array([gains[n]["kd"] for n in self.joint_order], dtype=np.float64),
            torque_limit=np.array([gains[n]["torque_limit"] for n in self.joint_order], dtype=np.float64),
        )
        self._kp = self.command.kp.copy()
        options = onnxruntime.SessionOptions()
        options.intra_op_num_threads = options.inter_op_num_threads = 1  # beside a real-time loop: one core
        self.session = onnxruntime.InferenceSession(str(onnx_path), options, providers=["CPUExecutionProvider"])
        self.observation = np.zeros((1, int(meta["observation_size"])), dtype=np.float32)
        self.action = np.zeros((1, j), dtype=np.float32)
        self._binding = self.session.io_binding()
        self._binding.bind_ortvalue_input("observation", onnxruntime.OrtValue.ortvalue_from_numpy(self.observation))
        self._binding.bind_ortvalue_output("action", onnxruntime.OrtValue.ortvalue_from_numpy(self.action))
        self._q, self._qd = np.zeros(j), np.zeros(j)  # policy order
        self._last, self._last_last = np.zeros(j), np.zeros(j)
        self._goal_tilt, self._goal_q = np.zeros(4), np.zeros(j)
        self._goal_gravity = np.zeros(3)  # the end pose's up axis (policies trained with env.observe_gravity)
        self._setpoint = np.zeros(j)  # policy order
        self.steps = 0  # policy steps since reset: t = steps * dt
        self.missed = 0  # steps without a state since reset
        self._started = False
        self._orientations: dict[str, tuple[EndPose, np.ndarray]] = {}  # name -> (pose, root quat), resolved once

    # ---- loading -------------------------------------------------------------------------

    @classmethod
    def load(cls, export_dir: str | Path, *, joint_order: Sequence[str] | None = None,
             on_missing: Literal["hold", "damp"] = "hold",
             sensitivity: Mapping[str, float] | None = None) -> "FallController":  # fmt: skip
        """The controller of `python -m fallkit mode=export` output: policy.onnx, policy.json and
        end_poses.json (the robot's artist poses, settled, when it ships any).

        joint_order: the order of the robot's joint arrays (default: the policy's, policy.json);
            states may also give joints by name (a mapping), in any order.
        on_missing: what `step(None)` does: "hold" the last setpoints, or "damp" (kp = 0).
        sensitivity: component -> weight, for a policy trained with env.sensitivity_inputs (see
            `set_sensitivity`); the others default to policy.json's.
        """
        folder = Path(export_dir)
        meta_path, onnx_path = folder / "policy.json", folder / "policy.onnx"
        meta = read_policy_json(folder)
        if not onnx_path.is_file():
            raise DeployError(f"{onnx_path} not found: export the policy with python -m fallkit mode=export checkpoint=<run>")
        missing = [k for k in _META_KEYS if k not in meta]
        if missing:
            raise DeployError(f"{meta_path}: lacks {missing}; export the policy with this fallkit version (mode=export)")
        poses_path = folder / "end_poses.json"
        poses = {}
        if poses_path.is_file():
            limits = meta["joint_limits"]
            for name, p in json.loads(poses_path.read_text()).items():
                # settled poses: exports written before settling clipped them hold joints up to ~0.01 rad past a
                # limit (sunk under load), which EndPose would refuse as a user's mistake
                joints = {j: min(max(float(q), limits[j][0]), limits[j][1]) if j in limits else q
                          for j, q in p["joints"].items()}  # fmt: skip
                poses[name] = EndPose(joints=joints, root_quat=tuple(p["root_quat"]))
        controller = cls(meta, onnx_path, poses, joint_order, on_missing)
        if sensitivity:
            controller.set_sensitivity(sensitivity)
        return controller

    def set_sensitivity(self, weights: Mapping[str, float]) -> None:
        """Change components' sensitivity weights (from the next step on): a just-damaged part weighs more.
        Only for policies trained with env.sensitivity_inputs; a weight outside the range the policy was
        trained on is used, with a warning (the policy never saw it)."""
        info = self.meta.get("sensitivity")
        if info is None:
            raise DeployError("set_sensitivity: this policy was trained without env.sensitivity_inputs, its "
                              "weights are fixed; retrain with env.sensitivity_inputs.enabled=true to set them")  # fmt: skip
        unknown = sorted(set(weights) - set(self.sensitivity))
        if unknown:
            raise DeployError(f"set_sensitivity: unknown components {unknown}; components are {list(self.sensitivity)}")
        checked = {}  # all or nothing: a bad weight leaves every weight as it was
        for c, w in weights.items():
            w = float(w) if isinstance(w, (int, float, np.number)) else math.nan
            if not math.isfinite(w) or w < 0:
                raise DeployError(f"set_sensitivity: the weight of '{c}' must be a finite number >= 0, got {weights[c]!r}")
            lo, hi = info["trained_range"][c]
            if not lo <= w <= hi:
                log.warning("sensitivity of '%s' = %g is outside the range the policy was trained on [%g, %g]", c, w, lo, hi)
            checked[c] = w
        self.sensitivity.update(checked)
        self._sensitivity_input[:] = np.log(np.maximum(list(self.sensitivity.values()), self._min_sensitivity))

    # ---- the loop ----------------------------------------------------------------------------

    def reset(self, end_pose: str | EndPose) -> None:
        """Start a fall toward `end_pose`: a name of end_poses.json, or an EndPose (joints by name
        with the ground side, or with the root orientation)."""
        if isinstance(end_pose, str):
            if end_pose not in self.end_poses:
                names = ", ".join(sorted(self.end_poses)) or "none: give an EndPose"
                raise DeployError(f"no end pose named '{end_pose}' in the export; its end poses: {names}")
            end_pose = self.end_poses[end_pose]
        q, quat = end_pose.resolve(self.joint_names, self.limits)
        self._goal_q[:] = q
        tilt_into(quat, self._goal_tilt)
        self._goal_gravity[:] = gravity_in_frame(self._goal_tilt)
        self.steps = self.missed = 0
        self._started = False

    def add_end_poses(self, poses: Mapping[str, EndPose]) -> None:
        """Name more end poses (your own list, a dataset's rows): `reset(name)` and `choose_end_pose`
        see them. Each is checked now (joints, limits, orientation), not in the middle of a fall."""
        for pose in poses.values():
            pose.resolve(self.joint_names, self.limits)
        self.end_poses.update(poses)

    def choose_end_pose(self, state: RobotState, names: Sequence[str] | None = None, sides: Sequence[str] | None = None,
                        pivot_height: float = PIVOT_HEIGHT) -> str:  # fmt: skip
        """The name of the end pose this fall is heading for: call it with the state the fall policy
        takes over at, then `reset(name)`.

        Candidates: the named end poses (end_poses.json and `add_end_poses`), only `names` if given,
        only those lying on one of `sides` (front, back, left, right, bottom, top) if given. The
        winner lies closest to where the fall heads: its capture point for an inverted pendulum of
        `pivot_height` (fallkit.pose_choice: the `heading` scorer of eval.poses=auto, the same code;
        the critic scorer needs privileged simulator state and is not exported).
        """
        check_state(state, self.joint_order, self._q, self._qd, self.to_policy)
        names = list(self.end_poses) if names is None else list(names)
        unknown = [n for n in names if n not in self.end_poses]
        if unknown or not names:
            raise DeployError(f"choose_end_pose: no end pose named '{unknown[0]}'" if unknown else
                              "choose_end_pose: no candidates: add_end_poses() first or name some")  # fmt: skip
        quats = np.array([self._orientation(n) for n in names])
        if sides is not None:
            bad = [s for s in sides if s not in SIDES]
            if bad:
                raise DeployError(f"choose_end_pose: unknown side {bad[0]!r}; sides are {', '.join(SIDES)}")
            rows = side_rows(quats, sides)
            if len(rows) == 0:
                there = ", ".join(f"{s} {k}" for s, k in side_counts(quats).items())
                raise DeployError(f"choose_end_pose: none of the {len(names)} candidates lies on {'/'.join(sides)}; "
                                  f"they lie on: {there}")  # fmt: skip
            names, quats = [names[i] for i in rows], quats[rows]
        quat, lin_vel = np.asarray(state.base_quat, dtype=np.float64)[None], np.asarray(state.base_lin_vel)[None]
        return names[int(choose_by_heading(quat, lin_vel, quats, pivot_height)[0])]

    def _orientation(self, name: str) -> np.ndarray:
        """The root quaternion of a named end pose, resolved once per pose object."""
        pose = self.end_poses[name]
        cached = self._orientations.get(name)
        if cached is None or cached[0] is not pose:
            cached = (pose, pose.resolve(self.joint_names, self.limits)[1])
            self._orientations[name] = cached
        return cached[1]

    def step(self, state: RobotState | None) -> Command:
        """One policy step: the command to apply until the next one (`None`: no estimate this step)."""
        if state is None:
            return self._missing()
        check_state(state, self.joint_order, self._q, self._qd, self.to_policy)
        if not self._started:  # the action history starts as a hold of the joints at the fall's start
            np.subtract(self._q, self.nominal, out=self._last)
            self._last /= self.action_scale
            self._last_last[:] = self._last
            self._started = True
        self._observe(state)
        self.session.run_with_iobinding(self._binding)
        a = self.action[0]
        np.multiply(a, self.action_scale, out=self._setpoint)
        self._setpoint += self.nominal
        if self.clip:
            np.clip(self._setpoint, self.limits[:, 0], self.limits[:, 1], out=self._setpoint)
        self._last_last[:] = self._last
        self._last[:] = a
        self.steps += 1
        np.take(self._setpoint, self.to_robot, out=self.command.setpoint)
        self.command.kp[:] = self._kp
        self.command.source = "policy"
        return self.command

    def _observe(self, state: RobotState) -> None:
        """The actor observation, in place (fallkit.env.observations.actor_observation)."""
        o, s = self.observation[0], self.slices
        tilt_into(state.base_quat, o[s["root_quat"]])
        o[s["root_lin_vel"]] = state.base_lin_vel
        o[s["root_ang_vel"]] = state.base_ang_vel
        o[s["joint_pos"]] = self._q
        o[s["joint_vel"]] = self._qd
        o[s["last_action"]] = self._last
        o[s["last_last_action"]] = self._last_last
        o[s["goal_root_quat"]] = self._goal_tilt
        o[s["goal_joint_pos"]] = self._goal_q
        o[s["blend"]] = tracking_blend(self.steps * self.dt, self.blend_time) if self.observe_blend else 0.0
        if "gravity" in s:  # yaw-invariant: the path-frame quaternion gives the world one's up axis
            o[s["gravity"]] = gravity_in_frame(o[s["root_quat"]])
            o[s["goal_gravity"]] = self._goal_gravity
        if "sensitivity" in s:
            o[s["sensitivity"]] = self._sensitivity_input

    def pose_from_file(self, path: str | Path, name: str) -> EndPose:
        """The pose `name` of an artist pose file (docs/poses.md), as authored (not settled)."""
        from fallkit.errors import PoseFileError, require_file
        from fallkit.pose_format import read_pose_entries

        entries = read_pose_entries(require_file(path, "artist pose", PoseFileError), self.meta["robot"],
                                    self.joint_names, self.limits)  # fmt: skip
        for e in entries:
            if e.name == name:
                return EndPose(joints=dict(zip(self.joint_names, e.joint_pos.tolist())), root_quat=tuple(e.root_quat))
        raise DeployError(f"{path}: no pose named '{name}'; its poses: {', '.join(e.name for e in entries)}")

    def _missing(self) -> Command:
        """No estimate this step: hold the last setpoints, or damp (kp = 0); time goes on."""
        self.missed += 1
        self.steps += 1
        if not self._started or self.on_missing == "damp":
            self.command.kp[:] = 0.0
            self.command.source = "damp"
        else:
            self.command.source = "hold"
        return self.command


# ---- the maths shared with the environment, in numpy --------------------------------------------


def tilt_into(quat: Sequence[float], out: np.ndarray) -> None:
    """The orientation in its path frame, heading removed, into `out`: (n, (wx + zy)/n, (wy − zx)/n, 0),
    n = |(w, z)| of the normalised quaternion (fallkit.env.observations.path_frame; identity heading
    when upside down exactly)."""
    w, x, y, z = quat
    norm = math.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / norm, x / norm, y / norm, z / norm
    n2 = w * w + z * z
    n = math.sqrt(n2)
    if n2 <= 1e-12:
        out[0], out[1], out[2], out[3] = n, x, y, 0.0
    else:
        out[0], out[1], out[2], out[3] = n, (w * x + z * y) / n, (w * y - z * x) / n, 0.0


def tracking_blend(t: float, blend_time: float) -> float:
    """u(t) = 3x² − 2x³, x = clamp(t / T_blend, 0, 1) (fallkit.env.rewards.tracking.blend)."""
    x = min(max(t / blend_time, 0.0), 1.0)
    return x * x * (3.0 - 2.0 * x)


def _check_layout(meta: dict, j: int) -> dict[str, slice]:
    """policy.json's observation layout must be the one this controller builds."""
    layout = meta["observation_layout"]
    names = tuple(p["name"] for p in layout)
    gravity = bool(meta.get("observe_gravity", False))  # exports made before the option existed: without
    expected = _LAYOUT + (("gravity", "goal_gravity") if gravity else ())
    expected += ("sensitivity",) if "sensitivity" in meta else ()
    if names != expected:
        raise DeployError(
            f"policy.json: observation layout {list(names)} is not the one this fallkit builds {list(expected)}; "
            "export the policy with the same fallkit version as this controller"
        )
    per_joint = {"joint_pos", "joint_vel", "last_action", "last_last_action", "goal_joint_pos"}
    sizes = {"root_quat": 4, "root_lin_vel": 3, "root_ang_vel": 3, "goal_root_quat": 4, "blend": 1, "gravity": 3,
             "goal_gravity": 3}
    if "sensitivity" in meta:
        sizes["sensitivity"] = len(meta["sensitivity"]["components"])
    out = {}
    for p in layout:
        want = j if p["name"] in per_joint else sizes[p["name"]]
        if p["size"] != want:
            raise DeployError(f"policy.json: observation part '{p['name']}' has size {p['size']}, expected {want}")
        out[p["name"]] = slice(p["start"], p["start"] + p["size"])
    return out


def _check_joint_order(order: list[str], names: list[str]) -> None:
    if sorted(order) != sorted(names):
        missing, extra = sorted(set(names) - set(order)), sorted(set(order) - set(names))
        raise DeployError(f"joint_order must name each policy joint once: missing {missing}, unknown {extra}")


__all__ = ["Command", "EndPose", "FallController", "RobotState", "tilt_into", "tracking_blend"]
