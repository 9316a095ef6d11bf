"""The artist pose file format: YAML end poses read and checked without torch or MuJoCo.

An artist file names, per pose, an angle for every joint and the side of the robot
that faces the ground (optionally refined by pitch and roll); docs/poses.md is the
authoring guide. `read_pose_entries` checks every key, angle and limit, failing with
one line '<file>:<line>: <where>: <problem>'. It needs only the robot's joint names
and limits, so the deploy controller (`fallkit.deploy`, numpy and onnxruntime alone)
reads the same files as training does; `fallkit.poses.artist` adds the checks that
need the simulator (self-collision) and the settling drop.
"""

from __future__ import annotations

import difflib
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import yaml

from fallkit.errors import PoseFileError

# side of the robot that faces the ground -> (pitch, roll) in degrees of the canonical orientation
GROUND_SIDES: dict[str, tuple[float, float]] = {
    "front": (90.0, 0.0),  # lying face down (prone)
    "back": (-90.0, 0.0),  # lying face up (supine)
    "left": (0.0, -90.0),  # lying on the left side
    "right": (0.0, 90.0),  # lying on the right side
    "bottom": (0.0, 0.0),  # upright: sitting, kneeling, standing
    "top": (180.0, 0.0),  # upside down, on the head
}
# the same sides as directions in the root frame (x forward, y left, z up)
_SIDE_AXES = {
    "front": (1, 0, 0), "back": (-1, 0, 0), "left": (0, 1, 0),
    "right": (0, -1, 0), "bottom": (0, 0, -1), "top": (0, 0, 1),
}  # fmt: skip
_AGREE_DEG = 60.0  # the named side must be within this angle of straight down
_UNITS = {"deg": math.pi / 180.0, "rad": 1.0, "°": math.pi / 180.0}
_ANGLE = re.compile(r"^\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*(deg|rad|°)?\s*$")
_TOP_KEYS = {"robot", "unit", "poses"}
_POSE_KEYS = {"name", "description", "root", "joints"}
_ROOT_KEYS = {"ground", "pitch", "roll"}


@dataclass
class ArtistPose:
    """An authored pose, validated, before settling."""

    name: str
    description: str
    joint_pos: np.ndarray  # [J] radians, policy order
    root_quat: np.ndarray  # [4] w, x, y, z
    ground: str
    line: int


class _Map(dict):
    """A YAML mapping that remembers the line of itself and of each key."""

    line: int = 0
    lines: dict[str, int]


class _DuplicateKey(Exception):
    def __init__(self, key: Any, line: int):
        super().__init__(key, line)
        self.key, self.line = key, line


class _LineLoader(yaml.SafeLoader):
    """YAML's safe loader whose mappings remember their lines (`_construct_mapping`, registered below)."""


def _construct_mapping(loader: _LineLoader, node: yaml.MappingNode) -> _Map:
    loader.flatten_mapping(node)
    out = _Map()
    out.line = node.start_mark.line + 1
    out.lines = {}
    for key_node, value_node in node.value:
        key = loader.construct_object(key_node, deep=True)
        if key in out:
            raise _DuplicateKey(key, key_node.start_mark.line + 1)
        out[key] = loader.construct_object(value_node, deep=True)
        out.lines[key] = key_node.start_mark.line + 1
    return out


_LineLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)


class _Reader:
    """Reads one artist pose file, raising PoseFileError '<file>:<line>: <where>: <problem>'."""

    def __init__(self, path: Path, robot: str, joint_names: Sequence[str], joint_limits: np.ndarray):
        self.path, self.robot = path, robot
        self.joint_names, self.joint_limits = list(joint_names), np.asarray(joint_limits, dtype=np.float64)

    def fail(self, line: int | None, where: str, problem: str) -> PoseFileError:
        at = f"{self.path}:{line}" if line else str(self.path)
        return PoseFileError(f"{at}: {where + ': ' if where else ''}{problem}")

    def parse(self) -> list[ArtistPose]:
        try:
            text = self.path.read_text()
        except OSError as exc:
            raise PoseFileError(f"{self.path}: cannot read artist pose file ({exc.strerror})") from None
        except UnicodeDecodeError:
            raise PoseFileError(f"{self.path}: not a text file (not UTF-8); an artist pose file is YAML text") from None
        try:
            doc = yaml.load(text, Loader=_LineLoader)
        except _DuplicateKey as exc:
            raise self.fail(exc.line, "", f"duplicate key '{exc.key}'") from None
        except yaml.YAMLError as exc:
            mark = getattr(exc, "problem_mark", None)
            problem = getattr(exc, "problem", None) or str(exc)
            raise self.fail(mark.line + 1 if mark else None, "", f"malformed YAML: {problem}") from None
        if not isinstance(doc, _Map):
            raise self.fail(1, "", "expected a mapping with the keys 'unit' and 'poses' (see docs/poses.md)")
        self.unknown_keys(doc, _TOP_KEYS, "")
        unit = self.required(doc, "unit", "", "the angle unit of this file, deg or rad")
        if unit not in ("deg", "rad"):
            raise self.fail(doc.lines["unit"], "unit", f"must be deg or rad, got {unit!r}")
        self.unit = unit
        poses = self.required(doc, "poses", "", "the list of poses")
        if not isinstance(poses, list) or not poses:
            raise self.fail(doc.lines["poses"], "poses", "expected a non-empty list of poses")
        out, seen = [], {}
        for i, p in enumerate(poses):
            pose = self.pose(p, i, doc.lines["poses"])
            if pose.name in seen:
                raise self.fail(pose.line, f"poses[{i}]", f"name '{pose.name}' is used twice (also line {seen[pose.name]})")
            seen[pose.name] = pose.line
            out.append(pose)
        return out

    def required(self, m: _Map, key: str, where: str, what: str) -> Any:
        if key not in m:
            raise self.fail(m.line, where, f"missing field '{key}' ({what})")
        return m[key]

    def unknown_keys(self, m: _Map, allowed: set[str], where: str) -> None:
        for k in m:
            if k not in allowed:
                raise self.fail(m.lines[k], where, f"unknown key '{k}'; allowed: {', '.join(sorted(allowed))}")

    def angle(self, value: Any, line: int, where: str) -> tuple[float, str]:
        """(radians, unit as written)."""
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            v, unit = float(value), self.unit
        elif isinstance(value, str) and (m := _ANGLE.match(value)):
            v, unit = float(m.group(1)), (m.group(2) or self.unit).replace("°", "deg")
        else:
            raise self.fail(line, where, f"expected an angle such as 45 or '-1.2 rad' or '30 deg', got {value!r}")
        if not math.isfinite(v):
            raise self.fail(line, where, f"angle must be finite, got {value!r}")
        return v * _UNITS[unit], unit

    def pose(self, p: Any, i: int, list_line: int) -> ArtistPose:
        where = f"poses[{i}]"
        if not isinstance(p, _Map):
            raise self.fail(list_line, where, "expected a mapping with name, root and joints")
        name = self.required(p, "name", where, "a short name for the pose")
        if not isinstance(name, str) or not name.strip():
            raise self.fail(p.lines["name"], f"{where}.name", f"expected a non-empty string, got {name!r}")
        where = f"poses[{i}] '{name}'"
        self.unknown_keys(p, _POSE_KEYS, where)
        desc = p.get("description", "")
        joints = self.required(p, "joints", where, "an angle for every joint of the robot")
        if not isinstance(joints, _Map):
            raise self.fail(p.lines["joints"], f"{where}.joints", "expected a mapping joint name -> angle")
        q = self.joints(joints, where)
        root = self.required(p, "root", where, "ground: front|back|left|right|bottom|top, optional pitch and roll")
        if not isinstance(root, _Map):
            raise self.fail(p.lines["root"], f"{where}.root", "expected a mapping with ground, pitch, roll")
        quat, ground = self.root(root, f"{where}.root")
        return ArtistPose(name, str(desc), q, quat, ground, p.line)

    def joints(self, joints: _Map, where: str) -> np.ndarray:
        names = self.joint_names
        lim = self.joint_limits
        for k in joints:
            if k not in names:
                close = difflib.get_close_matches(str(k), names, n=1)
                hint = f"; did you mean '{close[0]}'?" if close else f"; joints are {', '.join(names)}"
                raise self.fail(joints.lines[k], f"{where}.joints", f"unknown joint '{k}' for robot '{self.robot}'{hint}")
        missing = [n for n in names if n not in joints]
        if missing:
            raise self.fail(joints.line, f"{where}.joints", f"missing joints {', '.join(missing)} (name every joint)")
        q = np.zeros(len(names))
        for j, n in enumerate(names):
            line = joints.lines[n]
            q[j], unit = self.angle(joints[n], line, f"{where}.joints.{n}")
            lo, hi = lim[j]
            if not lo - 1e-6 <= q[j] <= hi + 1e-6:
                s = 1.0 / _UNITS[unit]
                side, bound, by = ("below the lower", lo, lo - q[j]) if q[j] < lo else ("above the upper", hi, q[j] - hi)
                raise self.fail(
                    line, f"{where}.joints.{n}",
                    f"{q[j] * s:.4g} {unit} is {side} limit {bound * s:.4g} {unit} by {by * s:.3g} {unit} "
                    f"(range [{lo * s:.4g}, {hi * s:.4g}] {unit})",
                )  # fmt: skip
            q[j] = min(max(q[j], lo), hi)
        return q

    def root(self, root: _Map, where: str) -> tuple[np.ndarray, str]:
        self.unknown_keys(root, _ROOT_KEYS, where)
        ground = self.required(root, "ground", where, f"the side facing the ground: {'|'.join(GROUND_SIDES)}")
        if ground not in GROUND_SIDES:
            raise self.fail(root.lines["ground"], f"{where}.ground", f"must be one of {', '.join(GROUND_SIDES)}, got {ground!r}")
        pitch0, roll0 = (math.radians(a) for a in GROUND_SIDES[ground])
        pitch = self.angle(root["pitch"], root.lines["pitch"], f"{where}.pitch")[0] if "pitch" in root else pitch0
        roll = self.angle(root["roll"], root.lines["roll"], f"{where}.roll")[0] if "roll" in root else roll0
        quat = root_quat_from_pitch_roll(pitch, roll)
        down = -gravity_in_frame(quat)
        off = math.degrees(math.acos(float(np.clip(down @ np.array(_SIDE_AXES[ground]), -1, 1))))
        if off > _AGREE_DEG:
            actual = ground_side(quat)
            raise self.fail(
                root.line, where,
                f"ground: {ground} disagrees with pitch {math.degrees(pitch):.4g} deg, roll {math.degrees(roll):.4g} deg, "
                f"which put the {actual} side on the ground ({off:.0f} deg from '{ground}'); fix the words or the numbers",
            )  # fmt: skip
        return quat, ground


def read_pose_entries(path: Path, robot: str, joint_names: Sequence[str], joint_limits: np.ndarray) -> list[ArtistPose]:
    """Every pose of an artist file, validated against the joints and limits (not self-collision)."""
    return _Reader(path, robot, joint_names, joint_limits).parse()


def root_quat_from_pitch_roll(pitch: float, roll: float) -> np.ndarray:
    """Upright, tipped by `pitch` about the world y axis (+ = forward), then rolled by `roll` about world x (+ = onto the right side)."""
    # q_roll(x) ⊗ q_pitch(y), multiplied out
    c1, s1, c2, s2 = math.cos(roll / 2), math.sin(roll / 2), math.cos(pitch / 2), math.sin(pitch / 2)
    return np.array([c1 * c2, s1 * c2, c1 * s2, s1 * s2])


def gravity_in_frame(quat: np.ndarray) -> np.ndarray:
    """R(q)ᵀ e_z: the world up axis in the frame of quaternions (w, x, y, z): [..., 4] -> [..., 3]
    (one quaternion of any shape holding 4 numbers -> [3])."""
    q = np.asarray(quat, dtype=np.float64)
    w, x, y, z = np.moveaxis(q.reshape(4) if q.size == 4 else q, -1, 0)
    return np.stack([2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)], axis=-1)


def ground_sides(quat: np.ndarray) -> np.ndarray:
    """The word for the side nearest to straight down of every orientation [P, 4] -> [P] (str): the one
    classification of lying poses that artist files (`ground`), dataset statistics and the end-pose
    choice's side restriction (fallkit.pose_choice) share."""
    down = -gravity_in_frame(np.asarray(quat, dtype=np.float64).reshape(-1, 4)).reshape(-1, 3)
    axes = np.array(list(_SIDE_AXES.values()), dtype=np.float64)  # [6, 3]
    return np.array(list(_SIDE_AXES))[(down @ axes.T).argmax(axis=1)]


def ground_side(quat: np.ndarray) -> str:
    """The word for the side of the robot nearest to straight down."""
    return str(ground_sides(quat)[0])
