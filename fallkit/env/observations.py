"""Actor and critic observations of the falling environment (paper Sec. IV-A, V-A).

The actor observation (what the robot can measure, plus the goal) is declared once,
in `ACTOR_OBSERVATION`: name, size and the noise level that applies to it. The
observation itself, its noise, the policy's joint prior (`fallkit.rl.models`) and the
export metadata (`fallkit.rl.export`) are all derived from that declaration, so the
order is written in one place. Gaussian noise goes on the measured parts only.

Critic (privileged): the noiseless actor observation, then
  phase           1  t / T
  friction        1  sliding friction of the contacts (per episode with env.randomization.friction)
  root_height     1  [m]
  body_height   B-1  height of every body [m]
  body_vel   6(B-1)  spatial velocity of every body (MuJoCo cvel: angular, linear about
                     the robot's centre of mass), rotated into the path frame;
                     component-major: ωx of all bodies, ωy …, then vx …
  body_acc   6(B-1)  Δ body_vel / policy_dt, same layout
Everything horizontal is expressed in the path frame, so both observations are
invariant under rotations of the world about z and horizontal translations.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import torch

from fallkit.config import ObservationNoise
from fallkit.robots.spec import RobotSpec
from fallkit.rotations import gravity_in_frame, quat_rotate_inverse

MIN_SENSITIVITY = 1e-3  # a weight of 0 is observed as this one: ln 0 is not a number


@dataclass(frozen=True)
class ObservationPart:
    """One named slice of the actor observation."""

    name: str
    size: int  # entries, or entries per joint when per_joint, per component when per_component
    per_joint: bool = False
    per_component: bool = False
    noise: str | None = None  # the ObservationNoise field giving its std; None: exact (actions, goal)
    doc: str = ""
    # How it reflects through the robot's sagittal plane (fallkit.env.mirror: quat, vector, pseudovector,
    # joint, scalar). No default on purpose: a new part without one is an error there, not a silent guess.
    mirror: str | None = None
    # The env option that adds this part (env.observe_gravity: "gravity"; env.sensitivity_inputs:
    # "sensitivity"); None: always observed. Optional parts come after every other part, so the columns
    # of the parts before them are the same with and without them.
    option: str | None = None

    def width(self, spec: RobotSpec) -> int:
        if self.per_component:
            return self.size * len(spec.components)
        return self.size * len(spec.joints) if self.per_joint else self.size


# The actor observation, in order (paper Sec. IV-A: s_t, then the goal g_t).
ACTOR_OBSERVATION: tuple[ObservationPart, ...] = (
    ObservationPart("root_quat", 4, noise="root_quat", doc="root orientation in the path frame (tilt_quat: heading removed, w >= 0)", mirror="quat"),
    ObservationPart("root_lin_vel", 3, noise="root_lin_vel", doc="root linear velocity, root frame [m/s]", mirror="vector"),
    ObservationPart("root_ang_vel", 3, noise="root_ang_vel", doc="root angular velocity, root frame [rad/s]", mirror="pseudovector"),
    ObservationPart("joint_pos", 1, per_joint=True, noise="joint_pos", doc="joint angles [rad]", mirror="joint"),
    ObservationPart("joint_vel", 1, per_joint=True, noise="joint_vel", doc="joint velocities [rad/s]", mirror="joint"),
    ObservationPart("last_action", 1, per_joint=True, doc="a_{t-1}, policy action units", mirror="joint"),
    ObservationPart("last_last_action", 1, per_joint=True, doc="a_{t-2}, policy action units", mirror="joint"),
    ObservationPart("goal_root_quat", 4, doc="end-pose root orientation in the path frame (see FallEnv)", mirror="quat"),
    ObservationPart("goal_joint_pos", 1, per_joint=True, doc="end-pose joint angles [rad]", mirror="joint"),
    ObservationPart("blend", 1, doc="u(t), the tracking blend of the time since the fall began (0 -> 1 over T_blend)", mirror="scalar"),
    ObservationPart("gravity", 3, noise="root_quat", doc="R(θ)ᵀe_z: the world up axis in the root frame (the orientation reward's vector)", mirror="vector", option="gravity"),
    ObservationPart("goal_gravity", 3, doc="R(θ̂)ᵀe_z: the world up axis in the end pose's root frame", mirror="vector", option="gravity"),
    ObservationPart("sensitivity", 1, per_component=True, doc=f"ln max(w_c, {MIN_SENSITIVITY:g}) of every component, robot order", mirror="component", option="sensitivity"),
)  # fmt: skip


@functools.cache  # called every env step: the layout is fixed per option pair
def observed_parts(sensitivity: bool = False, gravity: bool = False) -> tuple[ObservationPart, ...]:
    """The parts of the actor observation, with or without the sensitivity inputs (env.sensitivity_inputs)
    and the up axes (env.observe_gravity)."""
    options = {"sensitivity": sensitivity, "gravity": gravity}
    return tuple(p for p in ACTOR_OBSERVATION if p.option is None or options[p.option])


def sensitivity_input(weights: torch.Tensor) -> torch.Tensor:
    """What the policy observes of sensitivity weights [.., C]: ln w, weights of 0 held at MIN_SENSITIVITY
    (log: drawn log-uniformly, a weight's meaning is its ratio to others)."""
    return weights.clamp(min=MIN_SENSITIVITY).log()


def actor_layout(spec: RobotSpec, sensitivity: bool = False, gravity: bool = False) -> list[tuple[str, int]]:
    """(name, size) of each part of the actor observation, in order; `sensitivity`, `gravity`: with those options."""
    return [(part.name, part.width(spec)) for part in observed_parts(sensitivity, gravity)]


def actor_slices(spec: RobotSpec, sensitivity: bool = False, gravity: bool = False) -> dict[str, slice]:
    """Columns of each part of the actor observation."""
    out, start = {}, 0
    for name, size in actor_layout(spec, sensitivity, gravity):
        out[name] = slice(start, start + size)
        start += size
    return out


def describe_actor_observation(spec: RobotSpec, sensitivity: bool = False, gravity: bool = False) -> list[dict]:
    """The layout as plain data (name, start, size, noise field, meaning): the export's metadata."""
    slices = actor_slices(spec, sensitivity, gravity)
    return [
        {"name": p.name, "start": slices[p.name].start, "size": p.width(spec), "noise": p.noise, "meaning": p.doc}
        for p in observed_parts(sensitivity, gravity)
    ]


def critic_layout(spec: RobotSpec, sensitivity: bool = False, gravity: bool = False) -> list[tuple[str, int]]:
    """(name, size) of each part of the critic observation, in order."""
    b = spec.mj_model().nbody - 1  # without the world body
    return [(f"actor.{n}", s) for n, s in actor_layout(spec, sensitivity, gravity)] + [
        ("phase", 1), ("friction", 1), ("root_height", 1), ("body_height", b), ("body_vel", 6 * b), ("body_acc", 6 * b),
    ]  # fmt: skip


# How the critic's privileged parts reflect (fallkit.env.mirror), by name as critic_layout gives them:
# per-body parts are permuted by the robot's body map; body motion is component-major (ω then v).
PRIVILEGED_MIRROR: dict[str, str] = {
    "phase": "scalar", "friction": "scalar", "root_height": "scalar",
    "body_height": "body", "body_vel": "body_motion", "body_acc": "body_motion",
}  # fmt: skip


def noise_std(
    spec: RobotSpec, noise: ObservationNoise, sensitivity: bool = False, gravity: bool = False
) -> torch.Tensor:
    """Per-dimension std [Da] of the actor noise (0 for the parts declared without noise)."""
    return torch.cat(
        [
            torch.full((p.width(spec),), getattr(noise, p.noise) * noise.scale if p.noise else 0.0)
            for p in observed_parts(sensitivity, gravity)
        ]
    )


@dataclass
class PathFrame:
    """The path frame of every world (paper Sec. IV-A), computed once per step.

    Origin at the root, x/y horizontal, x along the root's heading; the heading is
    the twist about world z of the root quaternion (`fallkit.rotations.heading_quat`).
    """

    tilt: torch.Tensor  # [N, 4] root orientation in the path frame (tilt_quat)
    heading: torch.Tensor  # [N, 2] (w, z) of the heading quaternion (w, 0, 0, z)
    cos: torch.Tensor  # [N, 1] cos ψ of the heading angle ψ
    sin: torch.Tensor  # [N, 1] sin ψ

    def into(self, v: torch.Tensor) -> torch.Tensor:
        """World vectors [N, ..., 3] expressed in the path frame (rotated by −ψ about z)."""
        shape = (-1,) + (1,) * (v.dim() - 2)
        c, s = self.cos.view(shape), self.sin.view(shape)
        x, y, z = v.unbind(-1)
        return torch.stack((c * x + s * y, c * y - s * x, z), dim=-1)

    def into_planar(self, x: torch.Tensor, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """x and y components [N, ...] of world vectors, rotated into the path frame."""
        shape = (-1,) + (1,) * (x.dim() - 1)
        c, s = self.cos.view(shape), self.sin.view(shape)
        return torch.addcmul(c * x, s, y), torch.addcmul(c * y, -s, x)

    def turn(self, q: torch.Tensor) -> torch.Tensor:
        """World orientation [N, 4] of path-frame orientations q: heading ⊗ q."""
        a, b = self.heading.unbind(-1)
        w, x, y, z = q.unbind(-1)
        # (a, 0, 0, b) ⊗ (w, x, y, z)
        return torch.stack((a * w - b * z, a * x - b * y, a * y + b * x, a * z + b * w), -1)


def path_frame(root_quat: torch.Tensor) -> PathFrame:
    """The path frames of root orientations [N, 4] (same results as heading_quat / tilt_quat, fewer ops)."""
    w, x, y, z = root_quat.unbind(-1)
    n2 = w * w + z * z
    ok = n2 > 1e-12  # upside down exactly: no heading, identity frame (as heading_quat)
    n = torch.sqrt(n2)
    inv = torch.where(ok, 1.0 / n, 0.0)
    hw, hz = torch.where(ok, w * inv, 1.0), z * inv
    tx = torch.where(ok, (w * x + z * y) * inv, x)
    ty = torch.where(ok, (w * y - z * x) * inv, y)
    tilt = torch.stack((n, tx, ty, 0.0 * n), -1)
    return PathFrame(
        tilt=tilt,
        heading=torch.stack((hw, hz), -1),
        cos=(hw * hw - hz * hz).unsqueeze(-1),
        sin=(2.0 * hw * hz).unsqueeze(-1),
    )


def actor_observation(
    frame: PathFrame,
    root_quat: torch.Tensor,
    root_lin_vel: torch.Tensor,
    root_ang_vel: torch.Tensor,
    joint_pos: torch.Tensor,
    joint_vel: torch.Tensor,
    last_action: torch.Tensor,
    last_last_action: torch.Tensor,
    goal_root_quat: torch.Tensor,
    goal_joint_pos: torch.Tensor,
    blend: torch.Tensor,
    sensitivity: torch.Tensor | None = None,
    gravity: bool = False,
) -> torch.Tensor:
    """Noiseless actor observation [N, Da]; root_lin_vel in world, root_ang_vel in root frame (as SimState).

    blend [N]: u(t), or zeros where the actor does not observe time (env.observe_blend=false).
    sensitivity [N, C]: the weights w_c of every world, for a policy with sensitivity inputs; None without.
    gravity: with the up axes of the root and of the end pose (env.observe_gravity).
    """
    parts = {
        "root_quat": frame.tilt,
        "root_lin_vel": quat_rotate_inverse(root_quat, root_lin_vel),
        "root_ang_vel": root_ang_vel,
        "joint_pos": joint_pos,
        "joint_vel": joint_vel,
        "last_action": last_action,
        "last_last_action": last_last_action,
        "goal_root_quat": goal_root_quat,
        "goal_joint_pos": goal_joint_pos,
        "blend": blend.view(-1, 1),
    }
    if gravity:  # yaw-invariant: the same from the world quaternion and from the path-frame one
        parts["gravity"] = gravity_in_frame(frame.tilt)
        parts["goal_gravity"] = gravity_in_frame(goal_root_quat)
    if sensitivity is not None:
        parts["sensitivity"] = sensitivity_input(sensitivity)
    return torch.cat([parts[p.name] for p in observed_parts(sensitivity is not None, gravity)], dim=-1)


def critic_observation(
    actor: torch.Tensor,
    frame: PathFrame,
    phase: torch.Tensor,
    friction: torch.Tensor,
    root_height: torch.Tensor,
    body_height: torch.Tensor,
    body_motion: torch.Tensor,
) -> torch.Tensor:
    """The critic observation [N, Dc]: the noiseless actor observation, then the privileged part.

    body_motion [N, 4, 3, B-1]: body angular and linear velocity, then angular and
    linear acceleration, world frame, in planar layout (components first, bodies
    last: contiguous rows make the rotation into the path frame cheap).
    """
    n = actor.shape[0]
    x, y = frame.into_planar(body_motion[:, :, 0], body_motion[:, :, 1])
    motion = torch.stack((x, y, body_motion[:, :, 2]), dim=2).view(n, -1)
    return torch.cat(
        (actor, phase.view(n, 1), friction.expand(n, 1), root_height.view(n, 1), body_height, motion), dim=-1
    )


def planar_motion(body_vel: torch.Tensor) -> torch.Tensor:
    """MuJoCo cvel [N, B, 6] (angular, linear) as [N, 2, 3, B]: vector, component, body."""
    n, b, _ = body_vel.shape
    return body_vel.transpose(1, 2).reshape(n, 2, 3, b)
