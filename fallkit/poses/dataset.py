"""Generated end-pose datasets: the versioned `.npz` file and its use as an `EndPoseSet`.

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
Files are written by `python -m fallkit mode=poses` (`fallkit.poses.generator`).
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from fallkit.errors import PoseFileError, require_file
from fallkit.poses.end_pose_set import EndPoseSet
from fallkit.robots.spec import RobotSpec

log = logging.getLogger(__name__)

FORMAT = "fallkit.end_poses"
VERSION = 1
SPLITS = ("train", "test")
_ARRAYS = ("joint_pos", "root_quat", "root_height", "split", "bin", "joint_names", "meta")

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
    path = require_file(path, "pose dataset", PoseFileError)
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
    _check_values(path, a)
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


def _first_bad(bad: np.ndarray) -> int | None:
    """The first row index where `bad` ([P] or [P, ...]) holds, or None."""
    rows = np.flatnonzero(bad.reshape(len(bad), -1).any(axis=1))
    return int(rows[0]) if len(rows) else None


def _check_values(path: Path, a: dict[str, np.ndarray]) -> None:
    """Every value a dataset brings, checked once at load: a NaN angle would otherwise flow into
    MuJoCo's controls ("Nan in CTRL") and the metrics (MJE nan) far from the file that caused it."""
    checks = [
        ("joint_pos", ~np.isfinite(a["joint_pos"]), "is not finite"),
        ("root_quat", ~np.isfinite(a["root_quat"]), "is not finite"),
        ("root_height", ~np.isfinite(a["root_height"]), "is not finite"),
        ("root_quat", np.abs(np.linalg.norm(np.nan_to_num(a["root_quat"], posinf=0.0, neginf=0.0), axis=-1) - 1.0) > 1e-3, "is not a unit quaternion"),
        ("split", ~np.isin(a["split"], SPLITS), f"is not one of {list(SPLITS)}"),
    ]
    for name, bad, problem in checks:
        row = _first_bad(bad)
        if row is not None:
            raise PoseFileError(
                f"{path}: array '{name}' row {row} {problem} ({a[name][row]!r}); "
                f"regenerate the dataset with python -m fallkit mode=poses"
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
    if isinstance(ds, PoseDataset):
        _check_limits(ds, spec, path)
    if robot != spec.name:
        log.info("end poses: %s was made for '%s', the same body as '%s' (model hash %s)", path, robot, spec.name, model_hash)


def _check_limits(ds: PoseDataset, spec: RobotSpec, path: str | Path) -> None:
    """Joint angles within the robot's limits (the generator clamps to them; 1e-3 rad float slack)."""
    lim = np.asarray(spec.joint_limits, dtype=np.float64)
    q = ds.joint_pos.astype(np.float64)
    excess = np.maximum(lim[:, 0] - q, q - lim[:, 1])  # > 0 outside
    row = _first_bad(excess > 1e-3)
    if row is not None:
        j = int(np.argmax(excess[row]))
        raise PoseFileError(
            f"{path}: array 'joint_pos' row {row}: joint '{ds.joint_names[j]}' = {q[row, j]:.4f} rad is outside its "
            f"limits [{lim[j, 0]:.4f}, {lim[j, 1]:.4f}] by {excess[row, j]:.4f} rad; "
            f"regenerate the dataset with python -m fallkit mode=poses robot={spec.name}"
        )


def take_count(n: int, fraction: float, where: str) -> int:
    """How many of n poses a `fraction` in (0, 1] takes: round(fraction x n), at least one."""
    if not (isinstance(fraction, (int, float)) and 0.0 < fraction <= 1.0):
        raise PoseFileError(f"{where}: fraction must be in (0, 1], got {fraction!r}")
    return max(1, round(fraction * n))


def dataset_end_poses(ds: PoseDataset, split: str, fraction: float, path: str | Path) -> EndPoseSet:
    """The first `fraction` of a split of `ds` as an EndPoseSet (`path` names the file in errors)."""
    if split not in SPLITS:
        raise PoseFileError(f"{path}: split must be one of {list(SPLITS)}, got {split!r}")
    rows = ds.rows(split)
    if len(rows) == 0:
        raise PoseFileError(f"{path}: the dataset has no '{split}' poses")
    rows = rows[: take_count(len(rows), fraction, str(path))]  # stored in random order: a prefix is a random subset
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
