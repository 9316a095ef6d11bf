"""Reward terms (paper Table I), each a small pure function of a batch context.

Modules: `context` (RewardContext, RewardConfig, the weighted sum), `impact`
(impact, root_acc), `tracking` (orientation, joints, the blend u(t)),
`regularization` (torques, joint_acc, action_rate, action_acc, offset). Every
term is registered under its name in the entry-point group `fallkit.rewards`.
"""

from fallkit.rewards.context import BUILTIN_TERMS, RewardConfig, RewardContext, RewardSum, RewardTerm

__all__ = ["BUILTIN_TERMS", "RewardConfig", "RewardContext", "RewardSum", "RewardTerm"]
