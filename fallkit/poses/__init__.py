"""End poses: the one home of everything about the poses a fall should end in (paper Sec. IV-C).

The set type (`EndPoseSet`), the self-collision checker (`PoseChecker`), settling a
pose by dropping it, orientation bins, the physics-informed generator, the versioned
dataset file, artist pose files, and `load_end_poses`, which turns any end-pose
source a config names into an `EndPoseSet`.
"""
