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


@dataclass
class EndPoseSet:
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

    def subset(self, index: torch.Tensor) -> "EndPoseSet":
        names = [self.names[i] for i in index.tolist()] if self.names else []
        return EndPoseSet(self.robot, self.joint_names, self.joint_pos[index], self.root_quat[index], names)
