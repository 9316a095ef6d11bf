"""The end pose a fall is heading for, chosen from the state it begins in (numpy only).

`eval.poses=auto` with `eval.scorer=heading`, and `FallController.choose_end_pose` on a robot
(docs/end_pose_choice.md). A pose the robot lands near is reached more easily than one it has
to roll into, so the candidate lying closest to where the fall is heading wins.

Where it is heading: the robot is an inverted pendulum of height L about its feet, and such a
pendulum falls toward its capture point, the divergent component of its motion ξ = lean + v / ω₀
(lean: the horizontal offset of the base above the feet, L × the horizontal part of the body's up
axis; v: the base's horizontal velocity; ω₀ = √(g / L)), the same quantity fall detectors watch.
It ends lying with its long axis on the ground, so the side facing the ground is the body
direction that now points along ξ, projected onto the plane across the long axis. Measured on
biped20 (docs/end_pose_choice.md) this predicts the landing better than the tilt advanced at its
current rate, at any horizon, and hardly depends on L (0.3 to 1.2 m).

It needs what a robot's estimator provides (base orientation and base-frame velocity): no
privileged knowledge, so mode=eval and the deployed controller share this one implementation and
choose alike. It imports numpy only, for `fallkit.deploy`.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from fallkit.pose_format import _SIDE_AXES, gravity_in_frame, ground_sides

# The sides a candidate can be restricted to (artist files' `ground` words, fallkit.pose_format).
SIDES: tuple[str, ...] = tuple(_SIDE_AXES)

# Default pendulum height (eval.heading_pivot_height) [m]: biped20's base stands 0.56 m above its
# feet; the prediction changed by < 1 degree between 0.3 and 1.2 m (docs/end_pose_choice.md).
PIVOT_HEIGHT = 0.5
GRAVITY = 9.81  # [m/s²]


def ground_directions(root_quat: np.ndarray) -> np.ndarray:
    """The side facing the ground as a unit vector in the root frame, −R(q)ᵀ e_z: [N, 4] -> [N, 3]."""
    return -gravity_in_frame(np.asarray(root_quat, dtype=np.float64).reshape(-1, 4)).reshape(-1, 3)


def capture_point(root_quat: np.ndarray, lin_vel: np.ndarray, pivot_height: float = PIVOT_HEIGHT) -> np.ndarray:
    """The fall's capture point ξ = lean + v / ω₀ [N, 3], a horizontal world vector written in the base frame [m].

    root_quat [N, 4] (w, x, y, z) in a z-up world frame (its heading does not matter), lin_vel [N, 3]
    the base's velocity in the base frame (a RobotState's base_lin_vel).
    """
    up = -ground_directions(root_quat)  # the world's up axis seen from the base
    v = np.asarray(lin_vel, dtype=np.float64).reshape(-1, 3)
    long_axis = np.array([0.0, 0.0, 1.0])
    lean = pivot_height * (long_axis - up[:, 2:3] * up)  # the body's up axis minus its vertical part
    v_horizontal = v - np.sum(v * up, axis=1, keepdims=True) * up
    return lean + v_horizontal / np.sqrt(GRAVITY / pivot_height)


def predicted_ground(root_quat: np.ndarray, lin_vel: np.ndarray, pivot_height: float = PIVOT_HEIGHT) -> np.ndarray:
    """The side [N, 3] (unit, base frame) expected to face the ground when the fall ends: the body direction
    along the capture point, across the long axis (lying). A fall without a direction keeps its current one."""
    xi = capture_point(root_quat, lin_vel, pivot_height)
    across = xi * np.array([1.0, 1.0, 0.0])
    norm = np.linalg.norm(across, axis=1, keepdims=True)
    return np.where(norm > 1e-9, across / np.maximum(norm, 1e-12), ground_directions(root_quat))


def heading_costs(predicted: np.ndarray, candidate_quat: np.ndarray) -> np.ndarray:
    """Angle [rad] between each fall's predicted ground direction [N, 3] and each candidate's [P, 4] -> [N, P]."""
    cos = predicted @ ground_directions(candidate_quat).T
    return np.arccos(np.clip(cos, -1.0, 1.0))


def choose_by_heading(
    root_quat: np.ndarray, lin_vel: np.ndarray, candidate_quat: np.ndarray, pivot_height: float = PIVOT_HEIGHT
) -> np.ndarray:
    """The candidate [N] (row of candidate_quat) whose ground direction is closest to where each fall is heading."""
    return heading_costs(predicted_ground(root_quat, lin_vel, pivot_height), candidate_quat).argmin(axis=1)


def side_rows(candidate_quat: np.ndarray, sides: Sequence[str]) -> np.ndarray:
    """Rows of the candidates lying on one of `sides` (front, back, left, right, bottom, top), in order.

    A pose lies on the side whose axis is nearest to straight down (fallkit.pose_format.ground_sides:
    the classification of artist files' `ground` and of the dataset's side shares).
    """
    unknown = [s for s in sides if s not in SIDES]
    if unknown:
        raise ValueError(f"unknown side {unknown[0]!r}; sides are {', '.join(SIDES)}")
    return np.flatnonzero(np.isin(ground_sides(candidate_quat), list(sides)))


def side_counts(candidate_quat: np.ndarray) -> dict[str, int]:
    """How many candidates lie on each side: what to tell a user whose restriction left none."""
    sides = ground_sides(candidate_quat)
    return {s: int((sides == s).sum()) for s in SIDES if (sides == s).any()}
