"""A reward term: penalize the root spinning, so the robot slides and crumples rather than rolls.

Switch it on with a weight: `python -m fallkit +reward.root_spin=0.5`. fallkit
multiplies the returned value by the weight and by the policy step dt.
"""

from __future__ import annotations

import torch

from fallkit.api import RewardContext


def root_spin(ctx: RewardContext) -> torch.Tensor:
    """−‖ω_root‖² [(rad/s)²], the root's angular velocity in its own frame; one value per world [N]."""
    return -ctx.state.root_ang_vel.square().sum(dim=-1)
