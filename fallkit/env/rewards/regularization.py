"""Regularization terms (paper Table I, bottom) and the positive offset."""

from __future__ import annotations

import torch

from fallkit.env.rewards.context import RewardContext


def torques(ctx: RewardContext) -> torch.Tensor:
    """−‖τ‖² [(N·m)²], actuator torques at the last physics substep."""
    return -ctx.state.joint_torque.square().sum(dim=-1)


def joint_acc(ctx: RewardContext) -> torch.Tensor:
    """−‖q̈‖² [(rad/s²)²], q̈ = Δq̇/policy_dt."""
    return -ctx.state.joint_acc.square().sum(dim=-1)


def action_rate(ctx: RewardContext) -> torch.Tensor:
    """−‖a_t − a_{t−1}‖², in policy action units (setpoint offset / action_scale)."""
    return -(ctx.action - ctx.last_action).square().sum(dim=-1)


def action_acc(ctx: RewardContext) -> torch.Tensor:
    """−‖a_t − 2a_{t−1} + a_{t−2}‖², in policy action units."""
    return -(ctx.action - 2.0 * ctx.last_action + ctx.last_last_action).square().sum(dim=-1)


def offset(ctx: RewardContext) -> torch.Tensor:
    """+1 per step: keeps early returns positive (paper Sec. IV-B)."""
    return torch.ones(ctx.action.shape[0], device=ctx.action.device)
