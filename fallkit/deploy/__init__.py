"""Deploy: the exported policy as a controller beside a robot's own (numpy and onnxruntime only).

`FallController.load(export_dir)`, `reset(end_pose)`, then `step(state)` every policy step;
see fallkit/deploy/controller.py and docs/deploy.md. `FallDetector.load(export_dir)` says when
to start a fall (fallkit/deploy/detector.py, docs/fall_detection.md). Importing this package
imports no torch, MuJoCo, Hydra or TorchRL, so it runs on a robot's computer.
"""

from fallkit.deploy.controller import Command, FallController
from fallkit.deploy.detector import FallDetector, FallSignals
from fallkit.deploy.state import EndPose, RobotState
from fallkit.errors import DeployError

__all__ = ["Command", "DeployError", "EndPose", "FallController", "FallDetector", "FallSignals", "RobotState"]
