"""`train.teachers`: a policy with sensitivity inputs learns from policies trained at fixed weights.

Every way of learning one policy over a range of sensitivity weights by PPO alone learned about their
average (docs/sensitivity_inputs.md: the weight-dependent part of the advantage is a small share of its
spread), while a policy trained at one weight learns that weight's behaviour in the same budget. So the
conditioned policy (the student) is given teachers: two or more runs of the same robot, each trained
without sensitivity inputs at weights that differ in one component only (the axis, e.g. the head at 1
and at 4). Each collected sample's target is the teachers' mean action at that state, blended linearly
in ln w of the axis component between the two teachers nearest the sample's drawn weight (the nearest
teacher beyond the ends), and PPO's loss gains α·Σ_j (μ_j − μ̂_j)²: kickstarting (Schmitt et al. 2018),
with PPO's own terms still learning beside it, so the student can improve on its teachers. With teachers
along several components (each teacher off the robot's weights in one component at most), the run draws
one component's weight per episode and each sample imitates the teachers of its drawn component.

The targets are computed once per batch (the teachers are frozen and the observations fixed): a forward
pass of each teacher over the batch, in float32, each on the columns of the student's observation that
it observed (its layout, matched by part name as train.init_from does).
"""

from __future__ import annotations

import logging
import math

import torch

from fallkit.config import FallkitConfig
from fallkit.env.observations import actor_layout, actor_slices, sensitivity_input
from fallkit.errors import CheckpointError, ConfigError
from fallkit.rl.init_from import ACTION_MEANING, column_map, observation_options, same_meaning
from fallkit.rl.policy import load_policy
from fallkit.robots.spec import RobotSpec

log = logging.getLogger(__name__)


class Teachers:
    """The frozen teachers of a run with `train.teachers.runs`, and their blend (`targets`).

    Each teacher's weights differ from this run's robot's in one component at most, so the teachers lie on
    axes through the robot's weights, one per such component: two or more teachers per axis (a teacher at the
    robot's own weights is on every axis). One axis: the run draws that component's weight
    (env.sensitivity_inputs.components=[it]). More: it draws one of them per episode (draw=one), so each
    sample is off the robot's weights along one axis at most, whose teachers it then imitates."""

    def __init__(self, config: FallkitConfig, spec: RobotSpec, device: torch.device | str = "cpu"):
        runs = config.train.teachers.runs
        now = config.model_dump(mode="json")
        options = observation_options(now)
        nets, columns, weights = [], [], []
        for i, run in enumerate(runs):
            say = f"train.teachers.runs[{i}]={run}"
            try:
                teacher = load_policy(run, device)
            except CheckpointError as exc:
                raise CheckpointError(f"{say}: {exc}") from None
            if teacher.spec.model_hash() != spec.model_hash():
                raise ConfigError(f"{say} was trained on robot '{teacher.spec.name}', another model than this run's "
                                  f"'{spec.name}': use teachers of the same robot model")  # fmt: skip
            if teacher.spec.component_names != spec.component_names:
                raise ConfigError(f"{say} has the components {teacher.spec.component_names}, this run's robot "
                                  f"'{spec.name}' {spec.component_names}: use teachers of the same components")  # fmt: skip
            theirs = teacher.config.model_dump(mode="json")
            same_meaning(theirs, now, say, ACTION_MEANING)
            if teacher.config.env.sensitivity_inputs.enabled:
                raise ConfigError(f"{say} observes its sensitivity weights: a teacher is a policy trained at fixed "
                                  "weights (env.sensitivity_inputs.enabled=false)")  # fmt: skip
            nets.append(teacher.module.module.net.requires_grad_(False))  # GaussianPolicyNet, float32, eval mode
            layout = actor_layout(spec, *observation_options(theirs))
            columns.append(column_map(layout, actor_layout(spec, *options), f"{say}: its actor observation").to(device))
            weights.append([float(w) for w in teacher.spec.sensitivity])
        self.nets, self.columns = nets, columns
        self.axes = _axes(spec, config, weights, runs)  # component -> [(teacher, weight)], by weight
        names = spec.component_names
        self.own = sensitivity_input(torch.as_tensor(spec.sensitivity, dtype=torch.float32, device=device))  # [C]
        first = actor_slices(spec, *options)["sensitivity"].start
        self.weight_columns = first + torch.arange(len(names), device=device)
        self.axis_ids = [names.index(c) for c in self.axes]
        self.points = [(torch.tensor([k for k, _ in p], device=device),
                        sensitivity_input(torch.tensor([w for _, w in p], device=device))) for p in self.axes.values()]  # fmt: skip
        log.info("train.teachers (α %g): %s", config.train.teachers.coef, "; ".join(
            f"{c} at {', '.join(f'{w:g} ({runs[k]})' for k, w in p)}" for c, p in self.axes.items()))  # fmt: skip

    @torch.no_grad()
    def targets(self, obs: torch.Tensor) -> torch.Tensor:
        """The teachers' blended mean action [..., A] for student observations `obs` [..., D]: along the axis of
        the component whose observed weight is off the robot's (the first axis where none is), linear in ln w
        between the two nearest teachers of that axis, the nearest one beyond its ends."""
        flat = obs.reshape(-1, obs.shape[-1]).float()
        actions = torch.stack([net(flat[:, cols])[0] for net, cols in zip(self.nets, self.columns)])  # [K, B, A]
        observed = flat[:, self.weight_columns]  # [B, C]
        off = (observed - self.own).abs() > 1e-4
        blend = torch.zeros(len(self.nets), flat.shape[0], device=flat.device)  # [K, B]: each teacher's share
        taken = ~off[:, self.axis_ids].any(-1)  # at the robot's weights: the first axis takes them
        for a, (component, (teachers, lw)) in enumerate(zip(self.axis_ids, self.points)):
            mine = off[:, component] | taken if a == 0 else off[:, component] & ~taken
            s = observed[:, component].clamp(lw[0], lw[-1])
            upper = torch.searchsorted(lw, s.contiguous(), right=True).clamp(1, len(lw) - 1)  # the teacher above s
            lower = upper - 1
            t = (s - lw[lower]) / (lw[upper] - lw[lower])
            share = torch.zeros_like(blend)
            share.scatter_(0, teachers[lower].unsqueeze(0), (1.0 - t).unsqueeze(0))
            share.scatter_add_(0, teachers[upper].unsqueeze(0), t.unsqueeze(0))
            blend = torch.where(mine, share, blend)
            taken |= mine
        return (blend.unsqueeze(-1) * actions).sum(0).reshape(*obs.shape[:-1], -1)


def _axes(spec: RobotSpec, config: FallkitConfig, weights: list[list[float]], runs: list[str]) -> dict[str, list]:
    """{component: [(teacher index, its weight of the component), …] sorted by weight} for every component some
    teacher weights differently from this run's robot; one-line errors for teachers that cannot teach this run."""
    names, own = spec.component_names, [float(w) for w in spec.sensitivity]
    offsets = []  # per teacher: the components it weights differently
    for k, w in enumerate(weights):
        off = [c for c in range(len(names)) if not math.isclose(w[c], own[c], rel_tol=1e-6)]
        if len(off) > 1:
            differ = ", ".join(f"{names[c]} {w[c]:g} vs {own[c]:g}" for c in off)
            raise ConfigError(f"train.teachers.runs[{k}]={runs[k]} weights {len(off)} components other than this run's "
                              f"robot ({differ}): a teacher may differ from it in one; set robot.sensitivity.<c> to the "
                              "weights the teachers share")  # fmt: skip
        offsets.append(off)
    base = [k for k, off in enumerate(offsets) if not off]  # teachers at the robot's own weights
    if len(base) > 1:
        raise ConfigError(f"train.teachers: {', '.join(runs[k] for k in base)} all weight like this run's robot; "
                          "one teacher per weight")  # fmt: skip
    axes = {}
    for c in sorted({off[0] for off in offsets if off}):
        points = sorted([(k, weights[k][c]) for k in base + [k for k, off in enumerate(offsets) if off == [c]]],
                        key=lambda p: p[1])  # fmt: skip
        if len(points) < 2 or len({w for _, w in points}) < len(points):
            raise ConfigError(f"train.teachers: the weight of {names[c]} needs teachers at two or more different "
                              f"weights (the robot's own, {own[c]:g}, counts): has {[w for _, w in points]}")  # fmt: skip
        axes[names[c]] = points
    if not axes:
        raise ConfigError("train.teachers: every teacher weights like this run's robot; teachers at other weights "
                          "of a component teach the policy to read that weight")  # fmt: skip
    inputs = config.env.sensitivity_inputs
    drawn = inputs.components or names
    if sorted(drawn) != sorted(axes):
        raise ConfigError(f"train.teachers teach the weights of {', '.join(axes)}: set 'env.sensitivity_inputs."
                          f"components=[{','.join(axes)}]' (this run draws {', '.join(drawn)})")  # fmt: skip
    if len(axes) > 1 and inputs.draw != "one":
        raise ConfigError(f"train.teachers along {len(axes)} components blend along one at a time: set "
                          "env.sensitivity_inputs.draw=one (one drawn weight per episode)")  # fmt: skip
    return axes
