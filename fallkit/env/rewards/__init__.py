"""Reward terms (paper Table I), each a small pure function of a batch context.

Modules: `context` (RewardContext, the weighted sum), `impact` (impact, root_acc),
`tracking` (orientation, joints, the blend u(t)), `regularization` (torques,
joint_acc, action_rate, action_acc, offset). Their weights are `fallkit.config.reward`.
Every term is registered under its name in the entry-point group `fallkit.rewards`.
"""

from fallkit.env.rewards.context import RewardContext, RewardSum, RewardTerm

__all__ = ["RewardContext", "RewardSum", "RewardTerm"]
