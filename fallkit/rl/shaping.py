"""Potential-based shaping of the orientation term: credit for steering the fall when it is steered.

The orientation term pays −u(t)‖R(θ)ᵀe_z − R(θ̂)ᵀe_z‖² late, as u(t) comes in, for a tilt that
was decided by the first half second of the fall. Learning that link is left to the critic
(measured: policies keep only 54–73 % of the falls the open-loop seek lands on the right side,
docs/training.md). Shaping the reward with F = γΦ(s') − Φ(s), Φ(s) = −c‖R(θ)ᵀe_z − R(θ̂)ᵀe_z‖²,
pays each step for the tilt it gained or lost toward the end pose, and leaves the optimal
policies of the task unchanged (Ng, Harada & Russell 1999: a potential-based term shifts
every value by −Φ and no action's advantage in the limit). It is a learning aid of PPO's: the
env's reward, the logged reward terms and the evaluation stay the task's. Measured with c = 20
(train=quick, 15 min): the orientation term learned no faster than without it, so it is off.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

from fallkit.env.observations import actor_slices
from fallkit.robots import RobotSpec
from fallkit.rotations import gravity_in_frame

SHAPED_REWARD = "shaped_reward"  # ("next", SHAPED_REWARD): what GAE reads when shaping is on


class OrientationPotential:
    """Φ(s) = −c‖R(θ)ᵀe_z − R(θ̂)ᵀe_z‖² read off the critic observation, which starts with the
    actor's noise-free parts: the root's and the end pose's orientation in the path frame (a yaw
    away from the world frame, which leaves R(·)ᵀe_z as it is)."""

    def __init__(self, spec: RobotSpec, scale: float, sensitivity: bool = False, gravity: bool = False):
        columns = actor_slices(spec, sensitivity, gravity)
        self.root, self.goal = columns["root_quat"], columns["goal_root_quat"]
        self.scale = float(scale)

    def __call__(self, critic_obs: torch.Tensor) -> torch.Tensor:
        """Φ of every row [..., 1]."""
        diff = gravity_in_frame(critic_obs[..., self.root]) - gravity_in_frame(critic_obs[..., self.goal])
        return -self.scale * diff.square().sum(dim=-1, keepdim=True)

    def shape(self, batch: TensorDictBase, gamma: float) -> None:
        """("next", SHAPED_REWARD) = reward + γΦ(s') − Φ(s), s' the state the step reached (at a
        truncation the last state of the episode, not the next episode's first)."""
        phi, phi_next = self(batch["critic"]), self(batch["next", "critic"])
        batch["next", SHAPED_REWARD] = batch["next", "reward"] + gamma * phi_next - phi
