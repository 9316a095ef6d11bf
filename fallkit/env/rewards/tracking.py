"""End-pose tracking terms (paper Table I, middle), blended in over time by u(t)."""

from __future__ import annotations

import torch

from fallkit.env.rewards.context import RewardContext
from fallkit.rotations import gravity_in_frame


def blend(t: torch.Tensor, blend_time: float) -> torch.Tensor:
    """u(t) = −2(t/T_blend)³ + 3(t/T_blend)² for t ≤ T_blend, then 1 (paper Sec. IV-B)."""
    x = (t / blend_time).clamp(0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def orientation(ctx: RewardContext) -> torch.Tensor:
    """−u(t)‖R(θ_t)ᵀe_z − R(θ̂_t)ᵀe_z‖², dimensionless (0 … 4).

    The world up axis seen from the root now and in the target orientation: a
    yaw-invariant comparison of the root's tilt (paper Table I).
    """
    diff = gravity_in_frame(ctx.state.root_quat) - gravity_in_frame(ctx.target_root_quat)
    return -ctx.blend * diff.square().sum(dim=-1)


def joints(ctx: RewardContext) -> torch.Tensor:
    """−u(t)‖q_t − q̂_t‖² [rad²]."""
    return -ctx.blend * (ctx.state.joint_pos - ctx.target_joint_pos).square().sum(dim=-1)
