"""End poses: the one home of everything about the poses a fall should end in (paper Sec. IV-C).

- `end_pose_set`: the set type `EndPoseSet` and `random_end_poses` (unsettled, for tests);
- `checker`: `PoseChecker`, self-collision, the lowest point, placing poses on the ground;
- `settle`: dropping poses with frozen joints until they rest;
- `bins`: orientation bins, the side facing the ground, and the train/test split;
- `balance`: how many poses each side and bin keeps (rebalancing: sides first, then bins);
- `generator`: the physics-informed generator of datasets (config section `dataset:`);
- `dataset`: the versioned dataset file (.npz);
- `artist`: artist pose files (.yaml);
- `sources`: `load_end_poses`, which turns any end-pose source a config names
  (`env.poses`, `eval.poses`) into an `EndPoseSet`.
"""

from fallkit.poses.checker import PoseChecker
from fallkit.poses.end_pose_set import EndPoseSet, random_end_poses
from fallkit.poses.sources import load_end_poses

__all__ = ["EndPoseSet", "PoseChecker", "load_end_poses", "random_end_poses"]
