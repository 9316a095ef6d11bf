"""A robot's left–right mirror map: derived from its names, checked on its geometry.

Symmetry augmentation (`train.ppo.mirror`) trains on every sample and on its mirror image,
the same fall reflected through the robot's sagittal plane. That is only right for a robot
that really is mirror-symmetric: a wrong map would silently teach the policy the physics of
a robot that does not exist. So the map is never written by hand:

  names   `left_*`/`right_*` pair joints and bodies, and so do `l_`/`r_`, `_l`/`_r`, `L_`/`R_`,
          `_left`/`_right` and legs `FL`/`FR`, `RL`/`RR`, `HL`/`HR`, `ML`/`MR`, `L1`/`R1`
          (any `_ - .`-separated token); a name without a side token maps to itself.
  axes    reflecting the world through its x–z plane (the robot faces +x, its left is +y)
          maps a hinge axis, a pseudo-vector, to (−ax, ay, −az) (a slide axis to (ax, −ay, az)).
          At the nominal pose that is the partner's axis (sign +1: both turn alike) or its
          negation (sign −1: the partner turns the other way); anything else is not symmetric.
  checks  the nominal pose, joint limits, damping, armature, springs, PD gains, the
          components and their sensitivity weights, and — at the nominal pose and at a
          generic pose with generic velocities — every body's position, centre of mass,
          mass, world-frame inertia and spatial velocity, every joint's anchor, and every
          geom's position, orientation, shape and contact parameters must mirror onto its
          partner's within `TOLERANCE`.

A robot that fails any check has no map, and a one-line reason says what and by how much.

Convention: the mirror of a vector x under a signed permutation (perm, sign) is
x'[i] = sign[i] · x[perm[i]]; every map here is an involution (applying it twice is the identity).
"""

from __future__ import annotations

import re
import sys
from dataclasses import dataclass
from typing import Any, Protocol

import mujoco
import numpy as np


class RobotSpec(Protocol):
    """What the mirror reads of a robot (fallkit.robots.spec.RobotSpec, which calls derive_mirror and
    so is not imported here)."""

    joints: Any
    components: Any

    @property
    def joint_names(self) -> list[str]: ...

    def mj_model(self) -> mujoco.MjModel: ...

    def nominal_q(self) -> np.ndarray: ...

# Model values are written in decimal text and mirrored ones are exact negations of each other, so a
# symmetric model agrees to rounding (biped20: to 2e-16); a millimetre or a gram is an asymmetric robot.
TOLERANCE = 1e-6

POLAR = np.array([1.0, -1.0, 1.0])  # a position, a velocity, a force: (x, −y, z)
PSEUDO = np.array([-1.0, 1.0, -1.0])  # an axis of rotation, an angular velocity: (−x, y, −z)
# plain ints: MuJoCo's enums do not compare equal to the numpy integers of the model arrays under `in`
_HINGE, _SLIDE, _BALL, _FREE = (int(t) for t in (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE,
                                                  mujoco.mjtJoint.mjJNT_BALL, mujoco.mjtJoint.mjJNT_FREE))  # fmt: skip
_SPHERE, _CAPSULE, _CYLINDER = (int(t) for t in (mujoco.mjtGeom.mjGEOM_SPHERE, mujoco.mjtGeom.mjGEOM_CAPSULE,
                                                 mujoco.mjtGeom.mjGEOM_CYLINDER))  # fmt: skip


@dataclass(frozen=True)
class MirrorMap:
    """The signed permutations that reflect a robot's state through its sagittal plane."""

    joint_perm: np.ndarray  # [J] policy order: partner of each actuated joint
    joint_sign: np.ndarray  # [J] +1 / −1
    body_perm: np.ndarray  # [nbody] MuJoCo body ids (0 = world, its own partner)
    qpos_perm: np.ndarray  # [nq] MuJoCo qpos layout
    qpos_sign: np.ndarray
    qvel_perm: np.ndarray  # [nv]
    qvel_sign: np.ndarray

    def mirror_joints(self, x):
        """Per-joint values [..., J] in policy order (angles, velocities, actions) of the mirror image."""
        return signed_permute(x, self.joint_perm, self.joint_sign)

    def mirror_qpos(self, qpos):
        """A MuJoCo qpos [..., nq] of the mirror image (free joints: (x, −y, z), quat (w, −x, y, −z))."""
        return signed_permute(qpos, self.qpos_perm, self.qpos_sign)

    def mirror_qvel(self, qvel):
        """A MuJoCo qvel [..., nv] of the mirror image (free joints: linear (x, −y, z), angular (−x, y, −z))."""
        return signed_permute(qvel, self.qvel_perm, self.qvel_sign)


def signed_permute(x, perm: np.ndarray, sign: np.ndarray):
    """x'[..., i] = sign[i] · x[..., perm[i]], for numpy arrays and torch tensors alike. torch is looked up,
    not imported: a tensor exists only once torch is loaded, and the robot registry (hence every config error)
    then starts without torch's 2-3 s import."""
    torch = sys.modules.get("torch")
    if torch is not None and isinstance(x, torch.Tensor):
        return x[..., torch.as_tensor(perm, device=x.device)] * torch.as_tensor(sign, dtype=x.dtype, device=x.device)
    return np.asarray(x)[..., perm] * sign


# ---- names ---------------------------------------------------------------------------------

_SEPARATORS = re.compile(r"([_\-.\s]+)")


def _swap_side(token: str) -> str:
    """The token naming the other side ('left' -> 'right', 'L' -> 'R', 'FL' -> 'FR', 'L1' -> 'R1'); else itself."""
    for a, b in (("left", "right"), ("right", "left"), ("l", "r"), ("r", "l")):
        if token.lower() == a:
            return b.upper() if token.isupper() else b.capitalize() if token[0].isupper() else b
    leg = re.fullmatch(r"([FfRrHhMm])([LlRr])", token)  # front / rear / hind / middle, then the side
    if leg:
        return leg[1] + _swap_side(leg[2])
    numbered = re.fullmatch(r"([LlRr])(\d+)", token)  # hexapod legs L1..L3 / R1..R3
    if numbered:
        return _swap_side(numbered[1]) + numbered[2]
    return token


def mirror_name(name: str) -> str:
    """The name of a joint's or body's mirror partner by the side conventions (itself when it has no side)."""
    parts = _SEPARATORS.split(name)
    return "".join(_swap_side(p) if i % 2 == 0 and p else p for i, p in enumerate(parts))


def _pair(names: list[str], what: str) -> list[int] | str:
    index = {n: i for i, n in enumerate(names)}
    pairs = []
    for i, name in enumerate(names):
        if not name:
            return f"{what} #{i} has no name, so it cannot be paired with its mirror partner"
        partner = mirror_name(name)
        if partner not in index:
            return f"{what} '{name}' has no mirror partner '{partner}'"
        pairs.append(index[partner])
    return pairs


# ---- the derivation ----------------------------------------------------------------------


def derive_mirror(spec: RobotSpec) -> MirrorMap | str:
    """The robot's mirror map, or a one-line reason why it has none (see the module docstring)."""
    m = spec.mj_model()
    joints = [m.joint(i).name for i in range(m.njnt)]
    bodies = [m.body(i).name for i in range(m.nbody)]
    jpair, bpair = _pair(joints, "joint"), _pair(bodies, "body")
    if isinstance(jpair, str) or isinstance(bpair, str):
        return jpair if isinstance(jpair, str) else bpair
    reason = _check_structure(m, joints, bodies, jpair, bpair)
    if reason:
        return reason

    data = mujoco.MjData(m)
    data.qpos[:] = _nominal_qpos(spec, m)
    mujoco.mj_forward(m, data)
    signs = _joint_signs(m, data, joints, jpair)
    if isinstance(signs, str):
        return signs
    mirror = _build(spec, m, jpair, bpair, signs)
    if isinstance(mirror, str):
        return mirror
    for check in (_check_nominal_pose, _check_joint_properties, _check_components):
        reason = check(spec, m, mirror)
        if reason:
            return reason
    rng = np.random.default_rng(0)
    generic_qpos, generic_qvel = _generic_state(m, rng)
    for what, qpos, qvel in (("the nominal pose", data.qpos, np.zeros(m.nv)), ("a generic pose", generic_qpos, generic_qvel)):
        reason = _check_pose(m, mirror, qpos, qvel, signs)
        if reason:
            return f"at {what}: {reason}"
    return mirror


def _check_structure(m: mujoco.MjModel, joints, bodies, jpair, bpair) -> str | None:
    """Partners of the same kind in partner places of the tree, and gravity in the mirror plane."""
    for j, p in enumerate(jpair):
        if m.jnt_type[j] == _BALL:
            return f"joint '{joints[j]}' is a ball joint: its mirror image is no signed joint angle"
        if m.jnt_type[p] != m.jnt_type[j]:
            return f"joints '{joints[j]}' and '{joints[p]}' are of different types"
        if m.jnt_bodyid[p] != bpair[m.jnt_bodyid[j]]:
            return f"joint '{joints[j]}' moves body '{bodies[m.jnt_bodyid[j]]}' but its partner '{joints[p]}' does not move that body's partner"
    for b, p in enumerate(bpair[1:], start=1):
        if m.body_parentid[p] != bpair[m.body_parentid[b]]:
            return f"body '{bodies[b]}' and its partner '{bodies[p]}' hang from bodies that are not partners"
    if abs(m.opt.gravity[1]) > TOLERANCE:
        return f"gravity {m.opt.gravity.tolist()} has a sideways (y) component"
    return None


def _nominal_qpos(spec: RobotSpec, m: mujoco.MjModel) -> np.ndarray:
    qpos = m.qpos0.copy()
    for name, value in zip(spec.joint_names, spec.nominal_q()):
        qpos[m.jnt_qposadr[m.joint(name).id]] = value
    return qpos


def _joint_signs(m: mujoco.MjModel, data: mujoco.MjData, joints, jpair) -> np.ndarray | str:
    """+1 / −1 per joint from the world-frame axes at the nominal pose (free joints: +1, unused)."""
    signs = np.ones(m.njnt)
    for j, p in enumerate(jpair):
        if int(m.jnt_type[j]) not in (_HINGE, _SLIDE):
            continue
        reflected = (PSEUDO if m.jnt_type[j] == _HINGE else POLAR) * data.xaxis[j]
        partner = data.xaxis[p]
        if np.abs(partner - reflected).max() < TOLERANCE:
            signs[j] = 1.0
        elif np.abs(partner + reflected).max() < TOLERANCE:
            signs[j] = -1.0
        else:
            return (f"joint '{joints[j]}': its axis {_vec(data.xaxis[j])} reflects to {_vec(reflected)}, but "
                    f"{'its partner ' + repr(joints[p]) if p != j else 'it'} turns about {_vec(partner)} at the nominal pose")  # fmt: skip
    return signs


def _build(spec: RobotSpec, m: mujoco.MjModel, jpair, bpair, signs: np.ndarray) -> MirrorMap | str:
    qpos_perm, qpos_sign = np.arange(m.nq), np.ones(m.nq)
    qvel_perm, qvel_sign = np.arange(m.nv), np.ones(m.nv)
    for j, p in enumerate(jpair):
        qa, qp, va, vp = m.jnt_qposadr[j], m.jnt_qposadr[p], m.jnt_dofadr[j], m.jnt_dofadr[p]
        if m.jnt_type[j] == _FREE:
            qpos_perm[qa : qa + 7], qpos_sign[qa : qa + 7] = qp + np.arange(7), [*POLAR, 1.0, -1.0, 1.0, -1.0]
            qvel_perm[va : va + 6], qvel_sign[va : va + 6] = vp + np.arange(6), [*POLAR, *PSEUDO]
        else:
            qpos_perm[qa], qpos_sign[qa] = qp, signs[j]
            qvel_perm[va], qvel_sign[va] = vp, signs[j]
    policy = {name: i for i, name in enumerate(spec.joint_names)}
    ids = [m.joint(name).id for name in spec.joint_names]
    partners = [m.joint(jpair[j]).name for j in ids]
    missing = [p for p in partners if p not in policy]
    if missing:  # a passive joint mirroring an actuated one: the actuators are not symmetric
        return f"joint '{missing[0]}' is the mirror partner of an actuated joint but is not actuated"
    return MirrorMap(
        joint_perm=np.array([policy[p] for p in partners]),
        joint_sign=signs[ids],
        body_perm=np.array(bpair),
        qpos_perm=qpos_perm, qpos_sign=qpos_sign, qvel_perm=qvel_perm, qvel_sign=qvel_sign,
    )  # fmt: skip


def _check_nominal_pose(spec: RobotSpec, m: mujoco.MjModel, mirror: MirrorMap) -> str | None:
    q = spec.nominal_q()
    mirrored = mirror.mirror_joints(q)
    i = int(np.argmax(np.abs(mirrored - q)))
    if abs(mirrored[i] - q[i]) > TOLERANCE:
        p = mirror.joint_perm[i]
        return (f"nominal_pose is not mirror-symmetric: {spec.joint_names[i]} = {q[i]:g} rad but its partner "
                f"{spec.joint_names[p]} = {q[p]:g} rad mirrors to {mirrored[i]:g}")  # fmt: skip
    return None


def _check_joint_properties(spec: RobotSpec, m: mujoco.MjModel, mirror: MirrorMap) -> str | None:
    """Limits (the partner's, negated and swapped when the sign is −1), damping, armature, friction, springs, gains."""
    names = spec.joint_names
    for i, p in enumerate(mirror.joint_perm):
        j, jp, s = m.joint(names[i]).id, m.joint(names[p]).id, mirror.joint_sign[i]
        lo, hi = m.jnt_range[jp] if s > 0 else -m.jnt_range[jp][::-1]
        if m.jnt_limited[j] != m.jnt_limited[jp] or (m.jnt_limited[j] and np.abs(m.jnt_range[j] - [lo, hi]).max() > TOLERANCE):
            return f"joint '{names[i]}': range {_vec(m.jnt_range[j])} is not the mirror {_vec([lo, hi])} of '{names[p]}''s"
        va, vp = m.jnt_dofadr[j], m.jnt_dofadr[jp]
        for field in ("dof_damping", "dof_armature", "dof_frictionloss"):
            if abs(getattr(m, field)[va] - getattr(m, field)[vp]) > TOLERANCE:
                return f"joints '{names[i]}' and '{names[p]}' differ in {field.removeprefix('dof_')}"
        if abs(m.jnt_stiffness[j] - m.jnt_stiffness[jp]) > TOLERANCE or (
            m.jnt_stiffness[j] and abs(m.qpos_spring[m.jnt_qposadr[j]] - s * m.qpos_spring[m.jnt_qposadr[jp]]) > TOLERANCE
        ):
            return f"joints '{names[i]}' and '{names[p]}' have springs that do not mirror"
        a, b = spec.joints[i], spec.joints[p]
        if (a.kp, a.kd, a.torque_limit) != (b.kp, b.kd, b.torque_limit):
            return f"joints '{names[i]}' and '{names[p]}' differ in PD gains or torque limit"
    return None


def _check_components(spec: RobotSpec, m: mujoco.MjModel, mirror: MirrorMap) -> str | None:
    """The mirror of each component is a component of the same sensitivity weight (the impact reward is then equal)."""
    names = list(spec.components)
    for name, partner in zip(names, _component_partners(spec, m, mirror)):
        if isinstance(partner, str):
            return f"component '{name}': the mirror of its bodies {partner} is not a component"
        w, v = spec.components[name].weight, spec.components[names[partner]].weight
        if w != v:
            return f"components '{name}' and '{names[partner]}' mirror each other but weigh {w:g} and {v:g}"
    return None


def component_permutation(spec: RobotSpec, mirror: MirrorMap) -> np.ndarray:
    """[C] the mirror partner of each component, robot order (derive_mirror checked that every one has one)."""
    return np.array(_component_partners(spec, spec.mj_model(), mirror), dtype=np.int64)


def _component_partners(spec: RobotSpec, m: mujoco.MjModel, mirror: MirrorMap) -> list[int | str]:
    """Index of each component's mirror image, or the sorted image bodies (a string) where it is no component."""
    sets = [set(c.bodies) for c in spec.components.values()]
    out: list[int | str] = []
    for c in spec.components.values():
        image = {m.body(int(mirror.body_perm[m.body(b).id])).name for b in c.bodies}
        out.append(sets.index(image) if image in sets else str(sorted(image)))
    return out



def _generic_state(m: mujoco.MjModel, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A pose with no symmetry of its own: tilted, turned and shifted root, joints spread within their limits."""
    qpos, qvel = m.qpos0.copy(), rng.normal(size=m.nv)
    for j in range(m.njnt):
        a = m.jnt_qposadr[j]
        if m.jnt_type[j] == _FREE:
            quat = np.array([0.8, 0.3, -0.4, 0.2])
            qpos[a : a + 7] = [0.31, 0.17, 0.83, *(quat / np.linalg.norm(quat))]
        elif m.jnt_limited[j]:
            lo, hi = m.jnt_range[j]
            qpos[a] = lo + (hi - lo) * rng.uniform(0.1, 0.9)
        else:
            qpos[a] = rng.uniform(-1.0, 1.0)
    return qpos, qvel


def _check_pose(m: mujoco.MjModel, mirror: MirrorMap, qpos: np.ndarray, qvel: np.ndarray, signs) -> str | None:
    """Everything physical of the mirrored state must be the mirror image of the state's."""
    a, b = mujoco.MjData(m), mujoco.MjData(m)
    a.qpos[:], a.qvel[:] = qpos, qvel
    b.qpos[:], b.qvel[:] = mirror.mirror_qpos(qpos), mirror.mirror_qvel(qvel)
    mujoco.mj_forward(m, a)
    mujoco.mj_forward(m, b)
    reflect = np.diag(POLAR)
    for i in range(1, m.nbody):
        p, name = mirror.body_perm[i], m.body(i).name
        inertia_a = a.ximat[i].reshape(3, 3) @ np.diag(m.body_inertia[i]) @ a.ximat[i].reshape(3, 3).T
        inertia_b = b.ximat[p].reshape(3, 3) @ np.diag(m.body_inertia[p]) @ b.ximat[p].reshape(3, 3).T
        scale_v = max(1.0, np.abs(a.cvel[i]).max())
        for what, dev, unit in (
            ("position", np.abs(b.xpos[p] - POLAR * a.xpos[i]).max(), "m"),
            ("centre of mass", np.abs(b.xipos[p] - POLAR * a.xipos[i]).max(), "m"),
            ("mass", abs(m.body_mass[p] - m.body_mass[i]) / max(m.body_mass[i], 1e-9), "(relative)"),
            ("inertia", np.abs(inertia_b - reflect @ inertia_a @ reflect).max() / max(np.abs(inertia_a).max(), 1e-12), "(relative)"),
            ("angular velocity", np.abs(b.cvel[p, :3] - PSEUDO * a.cvel[i, :3]).max() / scale_v, "(relative)"),
            ("linear velocity", np.abs(b.cvel[p, 3:] - POLAR * a.cvel[i, 3:]).max() / scale_v, "(relative)"),
        ):  # fmt: skip
            if dev > TOLERANCE:
                image = "its own mirror image" if p == i else f"the mirror image of '{name}''s"
                amount = f"{dev * 1000:.3g} mm" if unit == "m" else f"{dev:.3g} {unit}"
                return f"body '{m.body(p).name}': {what} differs from {image} by {amount}"
    for j in range(m.njnt):
        p = _joint_partner(m, mirror, j)
        dev = np.abs(b.xanchor[p] - POLAR * a.xanchor[j]).max()
        if int(m.jnt_type[j]) in (_HINGE, _SLIDE):
            reflected = (PSEUDO if m.jnt_type[j] == _HINGE else POLAR) * a.xaxis[j]
            dev = max(dev, np.abs(b.xaxis[p] - signs[j] * reflected).max())
        if dev > TOLERANCE:
            return f"joint '{m.joint(p).name}': anchor or axis differs from the mirror of '{m.joint(j).name}''s by {dev:.3g}"
    return _check_geoms(m, mirror, a, b)


def _joint_partner(m: mujoco.MjModel, mirror: MirrorMap, j: int) -> int:
    """The partner of model joint j, read off the qvel map (a joint's first dof identifies it)."""
    return int(m.dof_jntid[mirror.qvel_perm[m.jnt_dofadr[j]]])


_GEOM_FIELDS = ("geom_size", "geom_friction", "geom_condim", "geom_contype", "geom_conaffinity", "geom_priority",
                "geom_solref", "geom_solimp", "geom_solmix", "geom_margin", "geom_gap", "geom_rbound")  # fmt: skip
# (not geom_dataid: the mirror image of a mesh is another mesh, of the same size and bounding radius)


def _check_geoms(m: mujoco.MjModel, mirror: MirrorMap, a: mujoco.MjData, b: mujoco.MjData) -> str | None:
    """Each geom has a partner on the partner body: same shape and contact parameters, mirrored placement."""
    for body in range(m.nbody):
        partner = mirror.body_perm[body]
        mine = range(m.body_geomadr[body], m.body_geomadr[body] + m.body_geomnum[body])
        theirs = range(m.body_geomadr[partner], m.body_geomadr[partner] + m.body_geomnum[partner])
        if len(mine) != len(theirs):
            return f"bodies '{m.body(body).name}' and '{m.body(partner).name}' have {len(mine)} and {len(theirs)} geoms"
        for g in mine:
            if not any(_geoms_mirror(m, a, g, b, h) for h in theirs):
                return f"geom '{m.geom(g).name or g}' of body '{m.body(body).name}' has no mirror image on '{m.body(partner).name}'"
    return None


def _geoms_mirror(m: mujoco.MjModel, a: mujoco.MjData, g: int, b: mujoco.MjData, h: int) -> bool:
    if m.geom_type[g] != m.geom_type[h] or np.abs(b.geom_xpos[h] - POLAR * a.geom_xpos[g]).max() > TOLERANCE:
        return False
    if any(np.abs(np.asarray(getattr(m, f)[g], float) - getattr(m, f)[h]).max() > TOLERANCE for f in _GEOM_FIELDS):
        return False
    # the axes the shape depends on, each up to its direction: none for a sphere, the long axis of a
    # capsule or cylinder, all three otherwise
    kind = int(m.geom_type[g])
    axes = [] if kind == _SPHERE else [2] if kind in (_CAPSULE, _CYLINDER) else [0, 1, 2]
    ra, rb = a.geom_xmat[g].reshape(3, 3), b.geom_xmat[h].reshape(3, 3)
    return all(min(np.abs(rb[:, k] - POLAR * ra[:, k]).max(), np.abs(rb[:, k] + POLAR * ra[:, k]).max()) < TOLERANCE for k in axes)


def _vec(v) -> str:
    return "(" + ", ".join(f"{x + 0.0:.3g}" for x in v) + ")"  # + 0.0: no "-0"
