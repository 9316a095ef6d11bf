"""FallDetector: says when a fall has begun, from the state the FallController reads (numpy only).

    detector = FallDetector.load("export")          # policy.json's fall_detector (mode=export)
    every step of the robot's own controller:
        if detector.update(state):                   # RobotState, as for the controller
            controller.reset(end_pose)               # the fall policy takes over from here

What it watches, and why (docs/fall_detection.md has the measurements):

- the **capture point** x_cp = x_com + v_com / ω0, ω0 = sqrt(g / z_com), and its signed distance
  outside the **support polygon** (the convex hull of the sole points on the ground). A standing
  robot whose capture point leaves the polygon cannot stop without a step (the linear inverted
  pendulum), so this says "fall" while the robot still looks upright: the longest lead time.
  The COM and the soles come from forward kinematics of the joint encoders in the base frame
  (the kinematic model exported with the policy), turned upright by the IMU's orientation; the
  COM velocity from the estimator's base velocity, the gyro and the joint velocities. Which sole
  points touch the ground is read from the kinematics too (those within `contact_height` of the
  lowest), so a foot that lifts or a foot that rolls onto its edge shrinks the polygon by itself,
  with no contact sensor.
- the **tilt** of the base's up axis from vertical (the IMU alone): a backstop that does not
  depend on the kinematic model or the velocity estimate.
- the **tilt rate** (horizontal part of the angular velocity) is measured and reported, not used
  in the rule: in the push test it warned later than the capture point (0.78 s against 0.88 s
  median, each at the lowest threshold no surviving push reached), and its threshold is a number
  to calibrate per robot where the capture point's has a physical zero, the polygon's edge.

Rule: a fall has begun when capture_distance > capture_margin or tilt > max_tilt, for
`confirm_steps` updates in a row; the answer then stays True until `reset()`. One update takes
0.27 ms (median, one core; benchmarks/fall_detection.py); the module imports numpy only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from fallkit.deploy.state import RobotState, check_state, read_policy_json
from fallkit.errors import DeployError

FORMAT = 1  # fallkit.robots.kinematics.FORMAT: the exported layout this detector reads
_MIN_HEIGHT = 1e-3  # [m] z_com below this (lying on the ground) would make ω0 infinite


@dataclass(frozen=True)
class DetectorSettings:
    """The thresholds (fallkit.config.detector.DetectorConfig documents each)."""

    capture_margin: float  # [m]
    max_tilt: float  # [rad]
    confirm_steps: int
    contact_height: float  # [m]


@dataclass
class FallSignals:
    """What one update measured."""

    tilt: float = 0.0  # [rad] the base's up axis from vertical
    tilt_rate: float = 0.0  # [rad/s] horizontal part of the base's angular velocity (world frame)
    capture_distance: float = 0.0  # [m] capture point outside the support polygon (negative: inside)
    com_height: float = 0.0  # [m] centre of mass above the lowest sole point
    support_points: int = 0  # sole points on the ground (within contact_height of the lowest)
    # in the upright frame at the base (world axes, origin at the base), for logs and plots:
    com: np.ndarray = field(default_factory=lambda: np.zeros(3))  # [m] centre of mass
    com_velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))  # [m/s] its velocity (world)
    capture_point: np.ndarray = field(default_factory=lambda: np.zeros(2))  # [m] x, y


class FallDetector:
    """The detector of one robot (see the module docstring)."""

    def __init__(self, meta: dict, joint_order: Sequence[str] | None = None):
        self.meta = meta
        self.settings = _settings(meta)
        self.joint_names: list[str] = list(meta["joint_names"])
        self.joint_order = list(joint_order) if joint_order is not None else list(self.joint_names)
        if sorted(self.joint_order) != sorted(self.joint_names):
            raise DeployError(f"joint_order must name each of the robot's joints once: {self.joint_names}")
        self.to_policy = np.array([self.joint_order.index(n) for n in self.joint_names])
        self.gravity = float(meta["gravity"])
        self._model(meta["bodies"], meta["soles"])
        self._q, self._qd = np.zeros(len(self.joint_names)), np.zeros(len(self.joint_names))
        self.signals = FallSignals()
        self.reset()

    @classmethod
    def load(cls, export_dir: str | Path, *, joint_order: Sequence[str] | None = None) -> "FallDetector":
        """The detector of a `python -m fallkit mode=export` folder (policy.json's fall_detector)."""
        path = Path(export_dir) / "policy.json"
        meta = read_policy_json(export_dir)
        if "fall_detector" not in meta:
            raise DeployError(f"{path}: has no fall_detector; export the policy with this fallkit version (mode=export)")
        if meta["fall_detector"] is None:
            raise DeployError(f"{path}: exported without a fall detector (robot '{meta.get('robot')}' names no feet); "
                              "export it again with detector.feet=[<body>,...]")  # fmt: skip
        return cls(meta["fall_detector"], joint_order)

    def reset(self) -> None:
        """Watch afresh (after the robot stood up again): the answer goes back to False."""
        self.triggered = False
        self.trigger_step: int | None = None  # update index (from reset) at which it said "fall"
        self.reason: str | None = None  # "capture point" | "tilt"
        self.steps = 0
        self._run = 0

    def update(self, state: RobotState) -> bool:
        """Measure `state`; True once a fall has begun (and from then on, until `reset()`)."""
        s = self.measure(state)
        cp = s.capture_distance > self.settings.capture_margin
        over = cp or s.tilt > self.settings.max_tilt
        self._run = self._run + 1 if over else 0
        if not self.triggered and self._run >= self.settings.confirm_steps:
            self.triggered, self.trigger_step = True, self.steps
            self.reason = "capture point" if cp else "tilt"
        self.steps += 1
        return self.triggered

    def measure(self, state: RobotState) -> FallSignals:
        """The signals of one state, without deciding anything (also left in `self.signals`)."""
        check_state(state, self.joint_order, self._q, self._qd, self.to_policy)
        up = _rotation(state.base_quat)  # base -> world
        omega = np.asarray(state.base_ang_vel, dtype=np.float64)
        com, com_vel = self._com(self._q, self._qd)
        com_vel += np.asarray(state.base_lin_vel, dtype=np.float64) + _cross(omega, com)
        com_w, vel_w, omega_w = up @ com, up @ com_vel, up @ omega
        soles = self._soles() @ up.T
        ground = soles[:, 2] - self._radius
        lowest = float(ground.min())
        support = soles[ground <= lowest + self.settings.contact_height, :2]
        height = max(float(com_w[2]) - lowest, _MIN_HEIGHT)
        capture = com_w[:2] + vel_w[:2] / math.sqrt(self.gravity / height)
        s = self.signals
        s.tilt = math.acos(min(1.0, max(-1.0, float(up[2, 2]))))
        s.tilt_rate = math.hypot(float(omega_w[0]), float(omega_w[1]))
        s.capture_distance = signed_distance(capture, convex_hull(support))
        s.com_height, s.support_points = height, len(support)
        s.com[:], s.com_velocity[:], s.capture_point[:] = com_w, vel_w, capture
        return s

    # ---- the kinematic model -----------------------------------------------------------------

    def _model(self, bodies: list[dict], soles: list[dict]) -> None:
        """Arrays of the exported kinematic tree (fallkit.robots.kinematics.kinematic_tree)."""
        names = [b["name"] for b in bodies]
        self._parent = [int(b["parent"]) for b in bodies]
        if self._parent[0] != -1 or any(not 0 <= p < i for i, p in enumerate(self._parent) if i):
            raise DeployError("fall_detector.bodies: not a tree listed parents first; export the policy again")
        self._pos = np.array([b["pos"] for b in bodies], dtype=np.float64)
        self._rot0 = np.array([_rotation(b["quat"]) for b in bodies])
        self._mass = np.array([b["mass"] for b in bodies], dtype=np.float64)
        self._body_com = np.array([b["com"] for b in bodies], dtype=np.float64)
        self._joints: list[list[tuple]] = []
        for b in bodies:
            joints = []
            for j in b["joints"]:
                if not 0 <= int(j["index"]) < len(self.joint_names):
                    raise DeployError(f"fall_detector.bodies: joint '{j['name']}' has no place in joint_names")
                k = _cross_matrix(np.asarray(j["axis"], dtype=np.float64))
                joints.append((int(j["index"]), np.asarray(j["axis"], float), np.asarray(j["anchor"], float),
                               float(j["ref"]), k, k @ k))  # fmt: skip
            self._joints.append(joints)
        self._sole_body = [names.index(s["body"]) for s in soles]
        self._sole_points = [np.asarray(s["points"], dtype=np.float64) for s in soles]
        self._radius = np.concatenate([np.asarray(s["radius"], dtype=np.float64) for s in soles])
        n, order = len(bodies), [(b, j[0]) for b, joints in enumerate(self._joints) for j in joints]
        self._R, self._p, self._eye = np.zeros((n, 3, 3)), np.zeros((n, 3)), np.eye(3)
        self._joint_body = np.array([b for b, _ in order], dtype=np.int64)  # joints in order of application
        self._joint_index = np.array([i for _, i in order], dtype=np.int64)
        self._axes, self._anchors = np.zeros((len(order), 3)), np.zeros((len(order), 3))

    def _com(self, q: np.ndarray, qd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(COM, its velocity from the joints alone) in the base frame; the body frames stay in self._R, self._p.

        The velocity: a hinge turning at q̇ about axis a through x moves the subtree it carries, of mass
        M_s and COM c_s, so the whole COM moves at Σ q̇ a × M_s (c_s − x) / M.
        """
        R, p, axes, anchors = self._R, self._p, self._axes, self._anchors
        k = 0
        for b, parent in enumerate(self._parent):
            if parent < 0:
                R[b], p[b] = self._eye, 0.0
            else:
                R[b] = R[parent] @ self._rot0[b]
                p[b] = p[parent] + R[parent] @ self._pos[b]
            for index, axis, anchor, ref, kk, kk2 in self._joints[b]:
                anchors[k] = p[b] + R[b] @ anchor
                axes[k] = R[b] @ axis
                angle = q[index] - ref
                R[b] = R[b] @ (self._eye + math.sin(angle) * kk + (1.0 - math.cos(angle)) * kk2)
                p[b] = anchors[k] - R[b] @ anchor
                k += 1
        weighted = self._mass[:, None] * (p + np.einsum("bij,bj->bi", R, self._body_com))
        mass = self._mass.copy()
        for b in range(len(self._parent) - 1, 0, -1):  # children after parents: sum subtrees upward
            weighted[self._parent[b]] += weighted[b]
            mass[self._parent[b]] += mass[b]
        jb = self._joint_body
        lever = weighted[jb] - mass[jb, None] * anchors
        velocity = qd[self._joint_index] @ np.cross(axes, lever)
        return weighted[0] / mass[0], velocity / mass[0]

    def _soles(self) -> np.ndarray:
        """Every sole point in the base frame [k, 3] (after _com placed the bodies)."""
        return np.concatenate([self._p[b] + pts @ self._R[b].T for b, pts in zip(self._sole_body, self._sole_points)])


# ---- the rule over a record, and the plane geometry ------------------------------------------------


def first_trigger(capture_distance: np.ndarray, tilt: np.ndarray, capture_margin: float, max_tilt: float,
                  confirm_steps: int = 1) -> int:  # fmt: skip
    """The update index at which `FallDetector.update` first says "fall" for recorded signals (-1: never).

    The same rule over a whole record at once, so that mode=detect sweeps the threshold without
    running the detector again per value (it checks that the two agree).
    """
    over = (np.asarray(capture_distance) > capture_margin) | (np.asarray(tilt) > max_tilt)
    if confirm_steps > 1:  # a run of confirm_steps: the count of True over the window equals its length
        count = np.convolve(over.astype(np.int64), np.ones(confirm_steps, dtype=np.int64))[: len(over)]
        over = count >= confirm_steps
    hits = np.flatnonzero(over)
    return int(hits[0]) if len(hits) else -1


def convex_hull(points: np.ndarray) -> np.ndarray:
    """The convex hull of 2-D points [k, 2], counter-clockwise, without collinear points (monotone chain)."""
    pts = sorted(set(map(tuple, np.round(points, 9).tolist())))
    if len(pts) <= 2:
        return np.array(pts, dtype=np.float64).reshape(-1, 2)

    def half(seq: list) -> list:
        out: list = []
        for p in seq:
            while len(out) >= 2 and _turn(out[-2], out[-1], p) <= 0:
                out.pop()
            out.append(p)
        return out[:-1]

    return np.array(half(pts) + half(pts[::-1]), dtype=np.float64)


def signed_distance(point: np.ndarray, hull: np.ndarray) -> float:
    """Distance of `point` outside the convex polygon `hull` (counter-clockwise) [m]; inside: minus the
    distance to the nearest edge. A hull of one or two points is a point or a segment (never inside)."""
    if len(hull) == 1:
        return float(np.linalg.norm(point - hull[0]))
    start, end = hull, np.roll(hull, -1, axis=0)
    edge = end - start
    length = np.linalg.norm(edge, axis=1)
    if len(hull) >= 3:
        outward = np.stack([edge[:, 1], -edge[:, 0]], axis=1) / length[:, None]
        inside = float(((point - start) * outward).sum(axis=1).max())
        if inside <= 0.0:
            return inside
    t = np.clip(((point - start) * edge).sum(axis=1) / (length * length), 0.0, 1.0)
    return float(np.linalg.norm(start + t[:, None] * edge - point, axis=1).min())


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a × b of two 3-vectors (np.cross costs ten times more on one pair)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def _turn(o: tuple, a: tuple, b: tuple) -> float:
    return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])


def _rotation(quat: Sequence[float]) -> np.ndarray:
    """The rotation matrix of a (w, x, y, z) quaternion (normalised here)."""
    w, x, y, z = (float(v) for v in quat)
    n = math.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / n, x / n, y / n, z / n
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])  # fmt: skip


def _cross_matrix(a: np.ndarray) -> np.ndarray:
    """K with K v = a × v (Rodrigues: R = I + sin θ K + (1 − cos θ) K²)."""
    return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])


def _settings(meta: dict) -> DetectorSettings:
    """The exported thresholds, each checked (one line naming the key)."""
    if meta.get("format") != FORMAT:
        raise DeployError(f"fall_detector: format {meta.get('format')!r} is not {FORMAT}; export the policy again")
    raw = meta["settings"]
    checks = {"capture_margin": lambda v: math.isfinite(v), "max_tilt": lambda v: 0 < v <= math.pi,
              "confirm_steps": lambda v: v >= 1 and float(v).is_integer(), "contact_height": lambda v: v > 0}  # fmt: skip
    for key, ok in checks.items():
        value = raw.get(key)
        if not isinstance(value, (int, float)) or not ok(value):
            raise DeployError(f"fall_detector.settings.{key}: {value!r} is not a valid value")
    return DetectorSettings(float(raw["capture_margin"]), float(raw["max_tilt"]), int(raw["confirm_steps"]),
                            float(raw["contact_height"]))  # fmt: skip


__all__ = ["DetectorSettings", "FallDetector", "FallSignals", "convex_hull", "first_trigger", "signed_distance"]
