"""What the controller reads: the robot's estimated state, and the end pose of a fall.

Frames and units (docs/deploy.md): the world frame has z up (gravity −z); the base is
the robot's root body (policy.json `robot`'s root, the trunk or pelvis); angles in
radians, velocities in rad/s and m/s.
"""

from __future__ import annotations

import difflib
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from fallkit.errors import DeployError
from fallkit.pose_format import _AGREE_DEG, _SIDE_AXES, GROUND_SIDES, gravity_in_frame, root_quat_from_pitch_roll

_QUAT_TOLERANCE = 1e-2  # |‖q‖ − 1| beyond this is a wrong input, not rounding


@dataclass
class RobotState:
    """One estimate of the robot's state, as a state estimator provides it.

    base_quat     (w, x, y, z) orientation of the base in the world frame (z up), unit norm
    base_ang_vel  [rad/s] angular velocity of the base, in the base frame (the IMU's gyro)
    base_lin_vel  [m/s] linear velocity of the base, in the base frame
    joint_pos     [rad] by joint name (a mapping, any order; extra names are ignored), or an
                  array in the controller's `joint_order`
    joint_vel     [rad/s] likewise
    """

    base_quat: Sequence[float]
    base_ang_vel: Sequence[float]
    base_lin_vel: Sequence[float]
    joint_pos: Mapping[str, float] | np.ndarray
    joint_vel: Mapping[str, float] | np.ndarray


@dataclass(frozen=True)
class EndPose:
    """The pose a fall should end in, like an entry of an artist pose file.

    joints     [rad] every policy joint by name
    ground     the side facing the ground: front | back | left | right | bottom | top,
               optionally refined by pitch and roll [rad] (docs/poses.md), or instead
    root_quat  the end orientation (w, x, y, z), e.g. from a generated dataset
    Only the tilt of the orientation matters: the controller removes its heading.
    """

    joints: Mapping[str, float]
    ground: str | None = None
    pitch: float | None = None
    roll: float | None = None
    root_quat: Sequence[float] | None = None

    def resolve(self, joint_names: Sequence[str], limits: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(joint angles [J] in `joint_names` order, within the limits; root quaternion [4])."""
        return _joint_angles(self.joints, joint_names, limits), self._orientation()

    def _orientation(self) -> np.ndarray:
        if (self.root_quat is None) == (self.ground is None):
            raise DeployError("EndPose: give either ground (with optional pitch and roll) or root_quat")
        if self.root_quat is not None:
            return _unit_quat(self.root_quat, "EndPose.root_quat")
        if self.ground not in GROUND_SIDES:
            raise DeployError(f"EndPose.ground must be one of {', '.join(GROUND_SIDES)}, got {self.ground!r}")
        pitch0, roll0 = (math.radians(a) for a in GROUND_SIDES[self.ground])
        pitch = pitch0 if self.pitch is None else float(self.pitch)
        roll = roll0 if self.roll is None else float(self.roll)
        quat = root_quat_from_pitch_roll(pitch, roll)
        off = math.degrees(math.acos(float(np.clip(-gravity_in_frame(quat) @ np.array(_SIDE_AXES[self.ground]), -1, 1))))
        if off > _AGREE_DEG:
            raise DeployError(
                f"EndPose: ground={self.ground} disagrees with pitch {math.degrees(pitch):.4g} deg, roll "
                f"{math.degrees(roll):.4g} deg ({off:.0f} deg from '{self.ground}'); fix the words or the numbers"
            )
        return quat


def _joint_angles(joints: Mapping[str, float], names: Sequence[str], limits: np.ndarray) -> np.ndarray:
    unknown = [k for k in joints if k not in names]
    if unknown:
        close = difflib.get_close_matches(str(unknown[0]), names, n=1)
        hint = f"; did you mean '{close[0]}'?" if close else f"; joints are {', '.join(names)}"
        raise DeployError(f"EndPose.joints: unknown joint '{unknown[0]}'{hint}")
    missing = [n for n in names if n not in joints]
    if missing:
        raise DeployError(f"EndPose.joints: missing joints {', '.join(missing)} (name every joint)")
    q = np.array([float(joints[n]) for n in names])
    for j, n in enumerate(names):
        lo, hi = limits[j]
        if not math.isfinite(q[j]) or not lo - 1e-6 <= q[j] <= hi + 1e-6:
            raise DeployError(f"EndPose.joints.{n} = {q[j]:.4g} rad is outside its limits [{lo:.4g}, {hi:.4g}] rad")
    return np.clip(q, limits[:, 0], limits[:, 1])


def _unit_quat(q: Sequence[float], where: str) -> np.ndarray:
    a = np.asarray(q, dtype=np.float64)
    if a.shape != (4,) or not np.isfinite(a).all():
        raise DeployError(f"{where}: expected 4 finite numbers (w, x, y, z), got {q!r}")
    norm = math.sqrt(float(a @ a))
    if abs(norm - 1.0) > _QUAT_TOLERANCE:
        raise DeployError(f"{where}: quaternion norm {norm:.4g} is not 1 (within {_QUAT_TOLERANCE}); normalise it")
    return a / norm


# ---- the per-step check: no numpy allocation on the path where the state is good -------------


def check_state(state: RobotState, joint_order: list[str], q: np.ndarray, qd: np.ndarray, to_policy: np.ndarray) -> None:
    """Validate `state` and write its joints in policy order into `q`, `qd` (DeployError on bad input)."""
    _vector(state.base_quat, 4, "state.base_quat")
    w, x, y, z = state.base_quat
    norm2 = w * w + x * x + y * y + z * z
    if abs(math.sqrt(norm2) - 1.0) > _QUAT_TOLERANCE:
        raise DeployError(f"state.base_quat: norm {math.sqrt(norm2):.4g} is not 1 (within {_QUAT_TOLERANCE}); normalise it")
    _vector(state.base_ang_vel, 3, "state.base_ang_vel")
    _vector(state.base_lin_vel, 3, "state.base_lin_vel")
    _joints(state.joint_pos, joint_order, q, to_policy, "state.joint_pos")
    _joints(state.joint_vel, joint_order, qd, to_policy, "state.joint_vel")


def _vector(v: Sequence[float], n: int, where: str) -> None:
    if len(v) != n:
        raise DeployError(f"{where}: expected {n} numbers, got {len(v)}")
    for i in range(n):
        if not math.isfinite(v[i]):
            raise DeployError(f"{where}[{i}] is {v[i]} (not finite)")


def _joints(values: Mapping[str, float] | np.ndarray, order: list[str], out: np.ndarray, to_policy: np.ndarray,
            where: str) -> None:  # fmt: skip
    """Joint values by name or in `order` -> `out` in policy order."""
    if isinstance(values, Mapping):
        try:
            for i, k in enumerate(to_policy):
                out[i] = values[order[k]]
        except KeyError:
            missing = [n for n in order if n not in values]
            raise DeployError(f"{where}: missing joints {missing}") from None
    else:
        if len(values) != len(order):
            raise DeployError(f"{where}: expected {len(order)} values in the controller's joint_order, got {len(values)}")
        np.take(values, to_policy, out=out)
    total = float(out.sum())
    if not math.isfinite(total):
        bad = order[int(to_policy[int(np.flatnonzero(~np.isfinite(out))[0])])]
        raise DeployError(f"{where}: joint '{bad}' is not finite")


def read_policy_json(folder: str | Path) -> dict:
    """policy.json of a `mode=export` folder, or one DeployError saying how to make it."""
    path = Path(folder) / "policy.json"
    if not path.is_file():
        raise DeployError(f"{path} not found: export the policy with python -m fallkit mode=export checkpoint=<run>")
    try:
        return json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DeployError(f"{path}: not a policy.json ({exc}); export the policy again") from None
