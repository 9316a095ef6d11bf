"""Left–right mirror images of observations and actions, for symmetry augmentation (`train.ppo.mirror`).

The mirror image of a fall is the same fall reflected through the robot's sagittal plane: y → −y
of the path frame (x along the heading, y to the robot's left), the frame every horizontal quantity
of the observations is expressed in. How each kind of quantity reflects, with M = diag(1, −1, 1):

  quat          (w, x, y, z) → (w, −x, y, −z): the rotation R becomes M R M (a tilt stays a tilt, z = 0)
  vector        (x, y, z) → (x, −y, z): linear velocities, in the path frame and in the root frame
                alike (the root's own frame reflects to M R M too: the root lies in the mirror plane)
  pseudovector  (x, y, z) → (−x, y, −z): angular velocities (a cross product flips with handedness)
  joint         permuted and signed by the robot's joint map (fallkit.robots.mirror). Joint angles
                are absolute and actions relative to the nominal pose (setpoint = nominal + s·a), yet
                both take the same signs: the map is only derived when the zero pose (the model's
                geometry, checked at a generic pose) and the nominal pose are mirror-symmetric, so
                mirrored setpoints are nominal + s·(mirrored actions). Angles, velocities, the last
                two actions, goal angles and actions all follow this one rule.
  scalar        unchanged: u(t), the episode phase, friction, root height
  component     permuted by the robot's component map: sensitivity inputs (env.sensitivity_inputs)
  body          permuted by the robot's body map: body heights
  body_motion   MuJoCo cvel (ω, v) per body in the component-major planar layout
                (fallkit.env.observations: ωx of every body, ωy, ωz, vx, vy, vz): the body map
                within each component, pseudovector signs for ω and vector signs for v

Each mirror is one signed permutation of columns, x'[i] = sign[i] · x[perm[i]], built once from the
observation declarations (`ACTOR_OBSERVATION`, `critic_layout`, `PRIVILEGED_MIRROR`) and the robot's
derived map, so applying it to a batch is a gather and a multiply, and applying it twice is the identity.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from fallkit.env.observations import ACTOR_OBSERVATION, PRIVILEGED_MIRROR, critic_layout, observed_parts
from fallkit.errors import ConfigError
from fallkit.robots.mirror import POLAR, PSEUDO, MirrorMap, component_permutation
from fallkit.robots.spec import RobotSpec

# Signs of the fixed-size kinds, component by component.
_FIXED_SIGNS = {"quat": (1.0, -1.0, 1.0, -1.0), "vector": tuple(POLAR), "pseudovector": tuple(PSEUDO)}


@dataclass(frozen=True)
class SignedPermutation:
    """x'[..., i] = sign[i] · x[..., index[i]] on the last dimension of a batch."""

    index: torch.Tensor  # [D] long
    sign: torch.Tensor  # [D] float32

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        return x[..., self.index] * self.sign.to(x.dtype)

    def to(self, device: torch.device | str) -> "SignedPermutation":
        return SignedPermutation(self.index.to(device), self.sign.to(device))


@dataclass(frozen=True)
class ObservationMirror:
    """The mirror images of a robot's actor observation, critic observation and action."""

    actor: SignedPermutation
    critic: SignedPermutation
    action: SignedPermutation

    def to(self, device: torch.device | str) -> "ObservationMirror":
        return ObservationMirror(self.actor.to(device), self.critic.to(device), self.action.to(device))


def observation_mirror(
    spec: RobotSpec, device: torch.device | str = "cpu", sensitivity: bool = False, gravity: bool = False
) -> ObservationMirror:
    """The robot's observation and action mirrors (`sensitivity`, `gravity`: observations with the sensitivity
    inputs, the up axes); a ConfigError naming the reason when it has no mirror map."""
    mirror = require_mirror_map(spec)
    options = (sensitivity, gravity)
    return ObservationMirror(
        actor_mirror(spec, mirror, *options), critic_mirror(spec, mirror, *options), action_mirror(spec, mirror)
    ).to(device)


def require_mirror_map(spec: RobotSpec) -> MirrorMap:
    """spec.mirror_map, or a one-line ConfigError saying why this robot cannot be mirrored."""
    if spec.mirror_map is None:
        raise ConfigError(
            f"train.ppo.mirror=true: robot '{spec.name}' is not left-right symmetric ({spec.mirror_reason}); "
            "set train.ppo.mirror=false"
        )
    return spec.mirror_map


def action_mirror(spec: RobotSpec, mirror: MirrorMap) -> SignedPermutation:
    """Actions [.., J]: the joint map (see the module docstring for why the nominal offset drops out)."""
    return _signed_permutation([_columns("joint", 0, len(spec.joints), mirror, spec)])


def actor_mirror(
    spec: RobotSpec, mirror: MirrorMap, sensitivity: bool = False, gravity: bool = False
) -> SignedPermutation:
    """The actor observation [.., Da], part by part as `ACTOR_OBSERVATION` declares it."""
    parts, start = [], 0
    for part in observed_parts(sensitivity, gravity):
        parts.append(_columns(_actor_kind(part.name), start, part.width(spec), mirror, spec))
        start += part.width(spec)
    return _signed_permutation(parts)


def critic_mirror(
    spec: RobotSpec, mirror: MirrorMap, sensitivity: bool = False, gravity: bool = False
) -> SignedPermutation:
    """The critic observation [.., Dc]: the actor's parts, then the privileged ones (`PRIVILEGED_MIRROR`)."""
    parts, start = [], 0
    for name, size in critic_layout(spec, sensitivity, gravity):
        if name.startswith("actor."):
            kind = _actor_kind(name.removeprefix("actor."))
        elif name in PRIVILEGED_MIRROR:
            kind = PRIVILEGED_MIRROR[name]
        else:
            raise ValueError(f"critic observation part '{name}' has no mirror rule: add it to PRIVILEGED_MIRROR")
        parts.append(_columns(kind, start, size, mirror, spec))
        start += size
    return _signed_permutation(parts)


def _actor_kind(name: str) -> str:
    kind = next(p.mirror for p in ACTOR_OBSERVATION if p.name == name)
    if kind is None:
        raise ValueError(f"actor observation part '{name}' declares no mirror rule (ObservationPart.mirror)")
    return kind


def _columns(kind: str, start: int, size: int, mirror: MirrorMap, spec: RobotSpec) -> tuple[np.ndarray, np.ndarray]:
    """(source column, sign) of each column of one part starting at `start`."""
    if kind == "scalar":
        return start + np.arange(size), np.ones(size)
    if kind in _FIXED_SIGNS:
        signs = np.array(_FIXED_SIGNS[kind])
        if size != len(signs):
            raise ValueError(f"a '{kind}' observation part has {len(signs)} entries, not {size}")
        return start + np.arange(size), signs
    if kind == "joint":
        _expect(size, len(spec.joints), kind)
        return start + mirror.joint_perm, mirror.joint_sign.astype(float)
    if kind == "component":
        _expect(size, len(spec.components), kind)
        return start + component_permutation(spec, mirror), np.ones(size)
    bodies = mirror.body_perm[1:] - 1  # the observations leave out the world body (MuJoCo id 0)
    if kind == "body":
        _expect(size, len(bodies), kind)
        return start + bodies, np.ones(size)
    if kind == "body_motion":
        _expect(size, 6 * len(bodies), kind)
        b = len(bodies)
        signs = np.concatenate((PSEUDO, POLAR))  # ωx ωy ωz vx vy vz, each a block of b bodies
        index = np.concatenate([start + k * b + bodies for k in range(6)])
        return index, np.repeat(signs, b)
    raise ValueError(f"unknown mirror rule '{kind}'")


def _expect(size: int, expected: int, kind: str) -> None:
    if size != expected:
        raise ValueError(f"a '{kind}' observation part of this robot has {expected} entries, not {size}")


def _signed_permutation(parts: list[tuple[np.ndarray, np.ndarray]]) -> SignedPermutation:
    index = np.concatenate([i for i, _ in parts])
    sign = np.concatenate([s for _, s in parts])
    return SignedPermutation(torch.as_tensor(index, dtype=torch.long), torch.as_tensor(sign, dtype=torch.float32))
