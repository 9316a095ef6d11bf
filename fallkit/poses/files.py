"""End-pose files: generated datasets (.npz) and artist pose files (.yaml).

`load_end_poses(source, spec, split, fraction)` is the one way in for every
user of end poses (training, evaluation, rendering). `source` is

- a dataset file `*.npz` written by `python -m fallkit mode=poses`,
- an artist pose file `*.yaml` (human-written; settled by the generator's drop
  procedure when loaded),
- `"default"`: the robot's shipped dataset `<robot>_poses.npz` next to its MJCF
  (for biped20: fallkit/robots/assets/biped20_poses.npz),
- `"artist"`: the robot's shipped artist poses `<robot>_artist_poses.yaml`.

The dataset format, version 1 (numpy `.npz`, no pickles):

    joint_pos   [P, J] float32  settled joint angles [rad], columns in `joint_names` order
    root_quat   [P, 4] float32  settled root orientation (w, x, y, z), world frame, z up
    root_height [P]    float32  settled root height above the floor [m]
    split       [P]    <U5      "train" | "test"
    bin         [P]    int16    orientation bin (see `meta.bins`)
    joint_names [J]    <U..     joint names
    meta        []     <U..     JSON: format, version, robot, model_hash, seed,
                                generator config, orientation bins, statistics

Rows of each split are stored in random order, so the first k rows of a split
are a uniform random subset of it (`fraction`, the paper's dataset-size study).
See docs/poses.md for authoring artist poses.
"""

from __future__ import annotations

import difflib
import json
import logging
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml

from fallkit.errors import PoseFileError
from fallkit.robots.spec import RobotSpec
from fallkit.rotations import gravity_in_frame, quat_from_euler, quat_mul
from fallkit.poses.end_pose_set import EndPoseSet

log = logging.getLogger(__name__)

FORMAT = "fallkit.end_poses"
VERSION = 1
SPLITS = ("train", "test")
_ARRAYS = ("joint_pos", "root_quat", "root_height", "split", "bin", "joint_names", "meta")




# ---- datasets -------------------------------------------------------------------------------


@dataclass
class PoseDataset:
    """A generated end-pose dataset with its provenance."""

    robot: str
    model_hash: str
    joint_names: list[str]
    joint_pos: np.ndarray  # [P, J] float32, radians
    root_quat: np.ndarray  # [P, 4] float32
    root_height: np.ndarray  # [P] float32
    split: np.ndarray  # [P] "train" | "test"
    bin: np.ndarray  # [P] int16
    meta: dict[str, Any]

    def __len__(self) -> int:
        return len(self.joint_pos)

    def rows(self, split: str) -> np.ndarray:
        return np.flatnonzero(self.split == split)


def save_dataset(path: str | Path, ds: PoseDataset) -> Path:
    """Write `ds` as a compressed .npz (format above); returns the path."""
    path = Path(path)
    if path.suffix != ".npz":
        raise PoseFileError(f"{path}: a pose dataset file must end in .npz")
    path.parent.mkdir(parents=True, exist_ok=True)
    meta = {"format": FORMAT, "version": VERSION, "robot": ds.robot, "model_hash": ds.model_hash, **ds.meta}
    with open(path, "wb") as f:  # a file object: numpy would append .npz to other names
        np.savez_compressed(
            f,
            joint_pos=ds.joint_pos.astype(np.float32),
            root_quat=ds.root_quat.astype(np.float32),
            root_height=ds.root_height.astype(np.float32),
            split=ds.split.astype("<U5"),
            bin=ds.bin.astype(np.int16),
            joint_names=np.array(ds.joint_names),
            meta=np.array(json.dumps(meta)),
        )
    return path


def read_meta(path: str | Path) -> dict[str, Any]:
    """The provenance of a dataset file, without loading its arrays."""
    path = Path(path)
    if not path.is_file():
        raise PoseFileError(f"{path}: pose dataset not found")
    try:
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
    except Exception as exc:  # not a zip, no meta, bad JSON
        raise PoseFileError(f"{path}: not a fallkit pose dataset ({type(exc).__name__}: {exc})") from None
    if meta.get("format") != FORMAT:
        raise PoseFileError(f"{path}: not a fallkit pose dataset (format {meta.get('format')!r})")
    if meta.get("version") != VERSION:
        raise PoseFileError(
            f"{path}: dataset format version {meta.get('version')} is not supported by this fallkit "
            f"(reads version {VERSION}); regenerate it with python -m fallkit mode=poses"
        )
    return meta


def load_dataset(path: str | Path) -> PoseDataset:
    """Read a dataset file (format and version checked, not yet the robot)."""
    path = Path(path)
    meta = read_meta(path)
    with np.load(path, allow_pickle=False) as z:
        missing = [k for k in _ARRAYS if k not in z.files]
        if missing:
            raise PoseFileError(f"{path}: pose dataset lacks the arrays {missing}")
        a = {k: z[k] for k in _ARRAYS}
    p, j = a["joint_pos"].shape if a["joint_pos"].ndim == 2 else (-1, -1)
    shapes_ok = (
        j == len(a["joint_names"])
        and a["root_quat"].shape == (p, 4)
        and a["root_height"].shape == (p,)
        and a["split"].shape == (p,)
        and a["bin"].shape == (p,)
    )
    if not shapes_ok:
        raise PoseFileError(f"{path}: pose dataset arrays have inconsistent shapes")
    return PoseDataset(
        robot=meta["robot"],
        model_hash=meta["model_hash"],
        joint_names=[str(n) for n in a["joint_names"]],
        joint_pos=a["joint_pos"],
        root_quat=a["root_quat"],
        root_height=a["root_height"],
        split=a["split"],
        bin=a["bin"],
        meta=meta,
    )


def check_robot(ds: PoseDataset | dict[str, Any], spec: RobotSpec, path: str | Path) -> None:
    """Refuse a dataset made for another robot body (model hash) or with other joints.

    The model hash covers everything that shapes the simulated body (MJCF,
    joints, gains, timestep). A robot that differs only in its sensitivity
    weights or component grouping (biped20_battery) has the same body, so the
    same poses are valid for it.
    """
    robot, model_hash = (ds["robot"], ds["model_hash"]) if isinstance(ds, dict) else (ds.robot, ds.model_hash)
    if model_hash != spec.model_hash():
        same = robot == spec.name
        raise PoseFileError(
            f"{path}: pose dataset made for robot '{robot}' (model hash {model_hash}), but robot '{spec.name}' "
            f"has model hash {spec.model_hash()}"
            + (": its MJCF, joints or timestep changed since" if same else ": another robot")
            + f"; generate poses for it with: python -m fallkit mode=poses robot={spec.name}"
        )
    if isinstance(ds, PoseDataset) and ds.joint_names != spec.joint_names:
        raise PoseFileError(f"{path}: dataset joints {ds.joint_names} differ from robot '{spec.name}' joints {spec.joint_names}")
    if robot != spec.name:
        log.info("end poses: %s was made for '%s', the same body as '%s' (model hash %s)", path, robot, spec.name, model_hash)


def _take(n: int, fraction: float, where: str) -> int:
    if not (isinstance(fraction, (int, float)) and 0.0 < fraction <= 1.0):
        raise PoseFileError(f"{where}: fraction must be in (0, 1], got {fraction!r}")
    return max(1, round(fraction * n))


def dataset_end_poses(ds: PoseDataset, split: str, fraction: float, path: str | Path) -> EndPoseSet:
    if split not in SPLITS:
        raise PoseFileError(f"{path}: split must be one of {list(SPLITS)}, got {split!r}")
    rows = ds.rows(split)
    if len(rows) == 0:
        raise PoseFileError(f"{path}: the dataset has no '{split}' poses")
    rows = rows[: _take(len(rows), fraction, str(path))]  # stored in random order: a prefix is a random subset
    return EndPoseSet(
        robot=ds.robot,
        joint_names=list(ds.joint_names),
        joint_pos=torch.from_numpy(ds.joint_pos[rows].astype(np.float32)),
        root_quat=torch.from_numpy(ds.root_quat[rows].astype(np.float32)),
    )


def default_dataset(spec: RobotSpec) -> Path:
    """The robot's shipped dataset: <robot>_poses.npz next to its MJCF, or one made for the same body."""
    folder = Path(spec.mjcf).parent
    own = folder / f"{spec.name}_poses.npz"
    if own.is_file():
        return own
    for other in sorted(folder.glob("*_poses.npz")):
        try:
            if read_meta(other).get("model_hash") == spec.model_hash():
                return other
        except PoseFileError:
            continue
    raise PoseFileError(
        f"robot '{spec.name}' ships no end-pose dataset ({own} not found); generate one with: "
        f"python -m fallkit mode=poses robot={spec.name} dataset.out={own}"
    )


# ---- artist poses -------------------------------------------------------------------------------

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
    pass


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

    def __init__(self, path: Path, spec: RobotSpec):
        self.path, self.spec = path, spec

    def fail(self, line: int | None, where: str, problem: str) -> PoseFileError:
        at = f"{self.path}:{line}" if line else str(self.path)
        return PoseFileError(f"{at}: {where + ': ' if where else ''}{problem}")

    def parse(self) -> list[ArtistPose]:
        try:
            text = self.path.read_text()
        except OSError as exc:
            raise PoseFileError(f"{self.path}: cannot read artist pose file ({exc.strerror})") from None
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
        names = self.spec.joint_names
        lim = self.spec.joint_limits
        for k in joints:
            if k not in names:
                close = difflib.get_close_matches(str(k), names, n=1)
                hint = f"; did you mean '{close[0]}'?" if close else f"; joints are {', '.join(names)}"
                raise self.fail(joints.lines[k], f"{where}.joints", f"unknown joint '{k}' for robot '{self.spec.name}'{hint}")
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
        down = -gravity_in_frame(torch.tensor(quat)).numpy()
        off = math.degrees(math.acos(float(np.clip(down @ np.array(_SIDE_AXES[ground]), -1, 1))))
        if off > _AGREE_DEG:
            actual = ground_side(quat)
            raise self.fail(
                root.line, where,
                f"ground: {ground} disagrees with pitch {math.degrees(pitch):.4g} deg, roll {math.degrees(roll):.4g} deg, "
                f"which put the {actual} side on the ground ({off:.0f} deg from '{ground}'); fix the words or the numbers",
            )  # fmt: skip
        return quat, ground


def root_quat_from_pitch_roll(pitch: float, roll: float) -> np.ndarray:
    """Upright, tipped by `pitch` about the world y axis (+ = forward), then rolled by `roll` about world x (+ = onto the right side)."""
    z = torch.zeros(1, dtype=torch.float64)
    p = torch.tensor([pitch], dtype=torch.float64)
    r = torch.tensor([roll], dtype=torch.float64)
    return quat_mul(quat_from_euler(r, z, z), quat_from_euler(z, p, z))[0].numpy()


def tilt_change_deg(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Angle [deg] between the ground directions of orientations a and b [n, 4] (heading ignored)."""
    ga, gb = gravity_in_frame(a.double()), gravity_in_frame(b.double())
    return torch.rad2deg(torch.acos((ga * gb).sum(-1).clamp(-1.0, 1.0)))


def ground_side(quat: np.ndarray | torch.Tensor) -> str:
    """The word for the side of the robot nearest to straight down."""
    down = -gravity_in_frame(torch.as_tensor(quat, dtype=torch.float64).reshape(-1, 4))[0].numpy()
    return max(_SIDE_AXES, key=lambda s: float(down @ np.array(_SIDE_AXES[s])))


def read_artist_poses(path: str | Path, spec: RobotSpec) -> list[ArtistPose]:
    """Parse and validate an artist pose file (limits, self-collision); not settled yet."""
    path = Path(path)
    if not path.is_file():
        raise PoseFileError(f"{path}: artist pose file not found")
    poses = _Reader(path, spec).parse()
    _check_self_collision(path, spec, poses)
    return poses


def _check_self_collision(path: Path, spec: RobotSpec, poses: list[ArtistPose]) -> None:
    import mujoco

    from fallkit.sim.base import Layout

    m = spec.mj_model()
    d = mujoco.MjData(m)
    lay = Layout(spec)
    for p in poses:
        q = lay.qpos(torch.tensor([[0.0, 0.0, 10.0]], dtype=torch.float64), torch.tensor(p.root_quat)[None], torch.tensor(p.joint_pos)[None])
        d.qpos[:] = q[0].numpy()
        mujoco.mj_forward(m, d)
        if d.ncon:
            pairs = sorted({tuple(sorted((m.geom(c.geom1).name, m.geom(c.geom2).name))) for c in d.contact[: d.ncon]})
            shown = ", ".join(f"{a}-{b}" for a, b in pairs[:4])
            raise PoseFileError(f"{path}:{p.line}: pose '{p.name}': the robot collides with itself ({shown})")


def settle_artist_poses(path: str | Path, spec: RobotSpec, poses: list[ArtistPose]) -> tuple[EndPoseSet, torch.Tensor]:
    """Drop the authored poses as the generator does; (settled EndPoseSet, settled qpos [n, nq])."""
    from fallkit.poses.generator import settle
    from fallkit.config import SettleConfig
    from fallkit.poses.checker import PoseChecker
    from fallkit.sim.base import Layout

    cfg = SettleConfig()
    lay = Layout(spec)
    n = len(poses)
    joints = torch.tensor(np.stack([p.joint_pos for p in poses]))
    quat = torch.tensor(np.stack([p.root_quat for p in poses]))
    qpos = lay.qpos(torch.zeros(n, 3, dtype=torch.float64), quat, joints)
    qpos, _ = PoseChecker(spec, chunk=max(1, n)).place_on_ground(qpos, cfg.drop_height)
    res = settle(spec, qpos, cfg)
    for i in np.flatnonzero(~res.settled.numpy()):
        raise PoseFileError(
            f"{path}:{poses[i].line}: pose '{poses[i].name}' did not come to rest within {cfg.max_time:g} s of "
            f"being dropped with frozen joints; it is not statically stable near this orientation"
        )
    settled_q = res.qpos[:, lay.joint_qpos]
    settled_quat = res.qpos[:, lay.root_qpos + 3 : lay.root_qpos + 7]
    tilt = tilt_change_deg(quat, settled_quat)
    moved = (settled_q - joints).abs().amax(dim=1)
    for i, p in enumerate(poses):
        if tilt[i] > 20.0 or moved[i] > 0.2:
            log.warning(
                "artist pose '%s' (%s:%d) changed while settling: it tipped over by %.0f deg, joints moved up to "
                "%.2f rad; the settled pose is used", p.name, path, p.line, float(tilt[i]), float(moved[i]),
            )  # fmt: skip
    ps = EndPoseSet(
        robot=spec.name,
        joint_names=list(spec.joint_names),
        joint_pos=settled_q.float(),
        root_quat=settled_quat.float(),
        names=[p.name for p in poses],
    )
    return ps, res.qpos


def artist_file(spec: RobotSpec) -> Path:
    """The robot's shipped artist poses: <robot>_artist_poses.yaml next to its MJCF (or the first one there)."""
    folder = Path(spec.mjcf).parent
    own = folder / f"{spec.name}_artist_poses.yaml"
    if own.is_file():
        return own
    others = sorted(folder.glob("*_artist_poses.yaml"))
    if others:
        return others[0]
    raise PoseFileError(f"robot '{spec.name}' ships no artist poses ({own} not found)")


# ---- the one entry point --------------------------------------------------------------------------


def load_end_poses(source: str | Path, spec: RobotSpec, split: str = "train", fraction: float = 1.0) -> EndPoseSet:
    """End poses for `spec` from a dataset (.npz), an artist file (.yaml), "default" or "artist".

    split: "train" | "test" (datasets; artist files have no split and ignore it).
    fraction: (0, 1], the first round(fraction × P) poses (at least one); nested
    and deterministic, a uniform random subset for generated datasets.
    """
    if str(source) == "default":
        path = default_dataset(spec)
    elif str(source) == "artist":
        path = artist_file(spec)
    else:
        path = Path(source)
    if path.suffix == ".npz":
        ds = load_dataset(path)
        check_robot(ds, spec, path)
        return dataset_end_poses(ds, split, fraction, path)
    if path.suffix in (".yaml", ".yml"):
        poses = read_artist_poses(path, spec)
        poses = poses[: _take(len(poses), fraction, str(path))]
        return settle_artist_poses(path, spec, poses)[0]
    raise PoseFileError(f"{path}: unknown end-pose source; expected a .npz dataset, a .yaml pose file, 'default' or 'artist'")
