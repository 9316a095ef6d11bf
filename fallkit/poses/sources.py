"""`load_end_poses`: any end-pose source a config names, as an `EndPoseSet`.

It is the one way in for every user of end poses (training, evaluation,
rendering; the config keys `env.poses` and `eval.poses`). `source` is

- a dataset file `*.npz` written by `python -m fallkit mode=poses` (`fallkit.poses.dataset`),
- an artist pose file `*.yaml` (human-written; settled by the generator's drop
  procedure when loaded, `fallkit.poses.artist`),
- `"default"`: the robot's shipped dataset `<robot>_poses.npz` next to its MJCF
  (for biped20: fallkit/robots/assets/biped20_poses.npz),
- `"artist"`: the robot's shipped artist poses `<robot>_artist_poses.yaml`.
"""

from __future__ import annotations

from pathlib import Path

from fallkit.errors import PoseFileError
from fallkit.poses.artist import artist_file, read_artist_poses, settle_artist_poses
from fallkit.poses.dataset import check_robot, dataset_end_poses, default_dataset, load_dataset, take_count
from fallkit.poses.end_pose_set import EndPoseSet
from fallkit.robots.spec import RobotSpec


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
        poses = poses[: take_count(len(poses), fraction, str(path))]
        return settle_artist_poses(path, spec, poses)[0]
    raise PoseFileError(f"{path}: unknown end-pose source; expected a .npz dataset, a .yaml pose file, 'default' or 'artist'")
