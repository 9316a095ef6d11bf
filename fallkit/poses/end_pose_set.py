"""EndPoseSet: the end poses an environment steers falls toward.

The common currency between the end-pose sources (generated datasets, artist
pose files) and their users (the environment, evaluation, rendering). Joint
angles are in the robot's policy order; the root orientation is the settled
orientation of the pose, of which only the tilt matters to the reward (the
goal is expressed in the path frame, paper Sec. IV-A).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from fallkit.poses.checker import PoseChecker
from fallkit.robots.spec import RobotSpec
from fallkit.rotations import quat_from_euler


@dataclass
class EndPoseSet:
    """End poses of one robot: joint angles (policy order) and settled root orientations."""

    robot: str
    joint_names: list[str]
    joint_pos: torch.Tensor  # [P, J] radians, policy order
    root_quat: torch.Tensor  # [P, 4] w, x, y, z
    names: list[str] = field(default_factory=list)  # optional labels (artist poses)

    def __post_init__(self) -> None:
        p, j = self.joint_pos.shape
        if self.root_quat.shape != (p, 4):
            raise ValueError(f"end poses: root_quat must be [{p}, 4], got {list(self.root_quat.shape)}")
        if j != len(self.joint_names):
            raise ValueError(f"end poses: {j} joint columns but {len(self.joint_names)} joint names")
        if self.names and len(self.names) != p:
            raise ValueError(f"end poses: {len(self.names)} names for {p} poses")

    def __len__(self) -> int:
        return self.joint_pos.shape[0]

    def to(self, device: torch.device | str) -> "EndPoseSet":
        return EndPoseSet(self.robot, self.joint_names, self.joint_pos.to(device), self.root_quat.to(device), self.names)


def random_end_poses(spec: RobotSpec, n: int, generator: torch.Generator) -> EndPoseSet:
    """n unsettled end poses: collision-free joints within limits, root pitch then yaw uniform in ±180°.

    For tests and quick experiments without a dataset (`load_end_poses` loads real ones): the poses
    are not dropped and settled, so some cannot be reached at rest.
    """
    joints = PoseChecker(spec).sample_joints(n, generator)
    pitch, yaw = ((2.0 * torch.rand(2, n, generator=generator, dtype=torch.float64) - 1.0) * torch.pi).unbind()
    quat = quat_from_euler(torch.zeros_like(pitch), pitch, yaw)
    return EndPoseSet(spec.name, spec.joint_names, joints.float(), quat.float())
