"""Impact terms (paper Table I, top): contact forces and root acceleration."""

from __future__ import annotations

import torch

from fallkit.env.rewards.context import RewardContext


def impact_by_component(ctx: RewardContext) -> torch.Tensor:
    """−(w_c ‖f_c‖∞)² of every component c [N, C] (force_unit²); `impact` is their sum.

    f_c is taken at the WORST physics substep of the policy step (the largest
    ‖f_c‖∞ over the substeps): a 1–3 kN impact peak lasts a few milliseconds and
    would be missed or diluted by the last substep or an average. Forces are
    converted to `force_unit` (kN by default: in newtons the term is ~10⁷ per step
    and swamps every other term) and each component of f_c is clipped at
    `force_clip` (10 kN in training, paper Sec. V-A) against solver spikes.
    Sensitivity weights w_c ≥ 0, so ‖w_c f_c‖∞ = w_c ‖f_c‖∞.
    """
    f = ctx.state.contact_force.abs().amax(dim=(1, 3))  # [N, C]: max over substeps and xyz, newtons
    f = f * (1.0 / ctx.force_unit)
    if ctx.force_clip is not None:
        f = f.clamp(max=ctx.force_clip)
    return -(f * ctx.sensitivity).square()


def impact(ctx: RewardContext) -> torch.Tensor:
    """−Σ_c (w_c ‖f_c‖∞)² [force_unit²], f_c the net contact force on component c (see `impact_by_component`)."""
    return impact_by_component(ctx).sum(dim=-1)


# Its summands, one per component: the environment reports them as separate reward columns, so a
# critic can keep a value per component (train.ppo.value_per_component; fallkit.env.rewards.context).
impact.by_component = impact_by_component


def root_acc(ctx: RewardContext) -> torch.Tensor:
    """−‖v̇_root‖² [(m/s²)²], v̇ = Δv/policy_dt of the root, world frame: the kinematic acceleration,
    gravity not subtracted (free fall gives ‖v̇‖ = 9.81; fallkit.sim.base, root_lin_acc)."""
    return -ctx.state.root_lin_acc.square().sum(dim=-1)
