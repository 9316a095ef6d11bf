"""Artist pose files: human-written end poses in YAML, validated and settled.

The format and its line-exact checks of keys, angles and limits are in
`fallkit.pose_format` (torch-free, shared with the deploy controller); reading a
file here adds the self-collision check, and `settle_artist_poses` drops the poses
as the generator does. See docs/poses.md for authoring artist poses.
"""

from __future__ import annotations

import logging
from pathlib import Path

import mujoco
import numpy as np
import torch

from fallkit.config import SettleConfig
from fallkit.errors import PoseFileError, require_file
from fallkit.pose_format import GROUND_SIDES, ArtistPose, ground_side, read_pose_entries, root_quat_from_pitch_roll
from fallkit.poses.checker import PoseChecker
from fallkit.poses.end_pose_set import EndPoseSet
from fallkit.poses.settle import settle
from fallkit.robots.spec import RobotSpec
from fallkit.rotations import gravity_in_frame
from fallkit.sim import Layout

log = logging.getLogger(__name__)

__all__ = [
    "GROUND_SIDES", "ArtistPose", "artist_file", "ground_side", "read_artist_poses", "root_quat_from_pitch_roll",
    "settle_artist_poses", "shipped_artist_file", "tilt_change_deg",
]  # fmt: skip


def tilt_change_deg(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Angle [deg] between the ground directions of orientations a and b [n, 4] (heading ignored)."""
    ga, gb = gravity_in_frame(a.double()), gravity_in_frame(b.double())
    return torch.rad2deg(torch.acos((ga * gb).sum(-1).clamp(-1.0, 1.0)))


def read_artist_poses(path: str | Path, spec: RobotSpec) -> list[ArtistPose]:
    """Parse and validate an artist pose file (limits, self-collision); not settled yet."""
    path = require_file(path, "artist pose", PoseFileError)
    poses = read_pose_entries(path, spec.name, spec.joint_names, spec.joint_limits)
    _check_self_collision(path, spec, poses)
    return poses


def _check_self_collision(path: Path, spec: RobotSpec, poses: list[ArtistPose]) -> None:
    """Refuse the first pose whose geoms touch each other, naming up to four touching pairs."""
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
    cfg = SettleConfig()
    n = len(poses)
    joints = torch.tensor(np.stack([p.joint_pos for p in poses]))
    quat = torch.tensor(np.stack([p.root_quat for p in poses]))
    checker = PoseChecker(spec, chunk=max(1, n))
    lay = checker.layout
    qpos, _ = checker.on_ground(quat, joints, cfg.drop_height)
    res = settle(spec, qpos, cfg)
    for i in np.flatnonzero(~res.settled.numpy()):
        raise PoseFileError(
            f"{path}:{poses[i].line}: pose '{poses[i].name}' did not come to rest within {cfg.max_time:g} s of "
            f"being dropped with frozen joints; it is not statically stable near this orientation"
        )
    # clipped to the limits as the generator does: MuJoCo's soft limits let a loaded joint sink a little
    # past them (sitting_legs_forward's elbows: 0.007 rad), and a target outside the limits is refused downstream
    lim = torch.as_tensor(spec.joint_limits, dtype=res.qpos.dtype)
    settled_q = res.qpos[:, lay.joint_qpos].clamp(lim[:, 0], lim[:, 1])
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


def shipped_artist_file(spec: RobotSpec) -> Path | None:
    """The robot's shipped artist poses, or None: they are optional (a new plugin ships none)."""
    try:
        return artist_file(spec)
    except PoseFileError:
        return None


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
