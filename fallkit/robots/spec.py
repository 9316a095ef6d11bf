"""RobotSpec: what fallkit needs to know about a robot, validated on load.

A robot is an MJCF of its kinematic tree (bodies, hinge joints, collision geoms,
inertias) plus the facts the MJCF does not hold: PD gains and torque limits of
each actuated joint in policy order, the named *components* with their
*sensitivity weights* (paper Sec. V-A), the nominal standing pose and rates.

`RobotSpec.mj_spec()` turns that into the simulated scene with MuJoCo's MjSpec:
a free joint on the root body, a floor, one position actuator (PD) per joint,
and one net-contact-force sensor per component body.  Every backend and tool
builds from this one scene, so they all simulate the same robot.

MJCF files from public model collections bring their own scene: actuators,
sensors, keyframes and a floor. fallkit drops them, with one warning per robot
(its PD actuators come from the JointSpecs, its floor carries `friction`, and a
second set would double the actuators or the ground contacts), and keeps the
rest of the file (lights, materials, other geoms).
"""

from __future__ import annotations

import hashlib
import logging
from functools import cached_property
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from fallkit.errors import RobotSpecError
from fallkit.robots.mirror import MirrorMap, derive_mirror

log = logging.getLogger(__name__)
_WARNED: set[tuple[str, str]] = set()  # (robot, mjcf) whose dropped scene elements were reported


class JointSpec(BaseModel):
    """One actuated joint: PD gains at the physics rate and the torque limit."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str
    kp: float = Field(gt=0, description="proportional gain [N·m/rad]")
    kd: float = Field(ge=0, description="derivative gain [N·m·s/rad]")
    torque_limit: float = Field(gt=0, description="actuator torque limit [N·m]")


class ComponentSpec(BaseModel):
    """A named group of bodies whose summed contact force is penalized together."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    bodies: list[str] = Field(min_length=1)
    weight: float = Field(ge=0, description="sensitivity weight w_c of the impact reward")


class RobotSpec(BaseModel):
    """A robot fallkit can simulate, train and evaluate.

    Stable public names: `joint_names` (policy order), `nominal_pose`
    (joint name -> radians) and `mj_model()`.
    """

    model_config = ConfigDict(extra="forbid", frozen=True, arbitrary_types_allowed=True)

    name: str = Field(min_length=1)
    mjcf: Path = Field(description="MJCF of the robot's kinematic tree, without floor or actuators")
    root_body: str
    joints: list[JointSpec] = Field(min_length=1, description="actuated joints in policy order")
    components: dict[str, ComponentSpec] = Field(min_length=1)
    nominal_pose: dict[str, float] = Field(description="standing pose, joint name -> rad")
    disturbance_bodies: dict[str, list[str]] = Field(
        default_factory=dict,
        description="bodies playing the roles of paper Table IV: hips, feet, elbows, pelvis, head",
    )
    policy_hz: float = Field(default=50.0, gt=0)
    timestep: float = Field(default=0.005, gt=0, description="physics timestep [s]")
    friction: float = Field(default=1.0, gt=0, description="floor sliding friction")

    @field_validator("mjcf")
    @classmethod
    def _mjcf_exists(cls, path: Path) -> Path:
        if not Path(path).is_file():
            raise ValueError(f"MJCF file not found: {path}")
        return Path(path)

    @model_validator(mode="after")
    def _consistent(self) -> "RobotSpec":
        names = self.joint_names
        dupes = {n for n in names if names.count(n) > 1}
        if dupes:
            raise ValueError(f"joints: duplicated joint names {sorted(dupes)}")
        unknown = sorted(set(self.nominal_pose) - set(names))
        if unknown:
            raise ValueError(f"nominal_pose: unknown joints {unknown}")
        seen: dict[str, str] = {}
        for comp, c in self.components.items():
            for body in c.bodies:
                if body in seen:
                    raise ValueError(f"components: body '{body}' is in both '{seen[body]}' and '{comp}'")
                seen[body] = comp
        ratio = 1.0 / (self.policy_hz * self.timestep)
        if abs(ratio - round(ratio)) > 1e-6:
            raise ValueError(f"policy_hz: 1/(policy_hz*timestep) = {ratio:g} must be a whole number of substeps")
        return self

    # ---- derived facts -------------------------------------------------------------

    @property
    def joint_names(self) -> list[str]:
        return [j.name for j in self.joints]

    @property
    def component_names(self) -> list[str]:
        return list(self.components)

    @property
    def sensitivity(self) -> np.ndarray:
        """Sensitivity weights w_c in component order."""
        return np.array([c.weight for c in self.components.values()])

    @property
    def substeps(self) -> int:
        """Physics steps per policy step (decimation)."""
        return round(1.0 / (self.policy_hz * self.timestep))

    @property
    def policy_dt(self) -> float:
        return 1.0 / self.policy_hz

    def with_sensitivity(self, weights: dict[str, float]) -> "RobotSpec":
        """A copy with some components' sensitivity weights replaced."""
        unknown = sorted(set(weights) - set(self.components))
        if unknown:
            raise RobotSpecError(
                f"robot '{self.name}': sensitivity: unknown components {unknown}; "
                f"components are {self.component_names}"
            )
        comps = {
            k: c.model_copy(update={"weight": float(weights.get(k, c.weight))}) for k, c in self.components.items()
        }
        return self.model_copy(update={"components": comps})

    def model_hash(self) -> str:
        """Hash of everything that shapes the simulated robot (MJCF text, gains, timestep).

        Datasets and checkpoints record it, so a pose set made for another robot
        or another model version is refused instead of silently misused.
        """
        h = hashlib.sha256(Path(self.mjcf).read_bytes())
        h.update(repr([j.model_dump() for j in self.joints]).encode())
        h.update(repr((self.root_body, self.timestep)).encode())
        return h.hexdigest()[:16]

    # ---- simulation scene ------------------------------------------------------------

    def mj_spec(self) -> mujoco.MjSpec:
        """The simulated scene as an editable MjSpec (see module docstring)."""
        try:
            spec = mujoco.MjSpec.from_file(str(self.mjcf))
        except Exception as exc:  # MuJoCo's parser errors carry the line
            raise RobotSpecError(f"robot '{self.name}': mjcf: cannot load {self.mjcf}: {exc}") from exc
        spec.option.timestep = self.timestep
        self._drop_own_scene(spec)
        root = spec.body(self.root_body)
        if root is None:
            raise RobotSpecError(f"robot '{self.name}': root_body: no body '{self.root_body}' in {self.mjcf}")
        if not root.joints:
            root.add_freejoint(name="root")

        spec.worldbody.add_geom(
            name="floor",
            type=mujoco.mjtGeom.mjGEOM_PLANE,
            size=[0, 0, 0.05],
            friction=[self.friction, 0.005, 0.0001],
            rgba=[0.55, 0.6, 0.65, 1],
        )
        spec.worldbody.add_light(pos=[0, 0, 3], dir=[0, 0, -1], diffuse=[0.8, 0.8, 0.8])
        for j in self.joints:
            if spec.joint(j.name) is None:
                raise RobotSpecError(f"robot '{self.name}': joints: no joint '{j.name}' in {self.mjcf}")
            act = spec.add_actuator(name=j.name, target=j.name, trntype=mujoco.mjtTrn.mjTRN_JOINT)
            # Position servo: tau = kp (ctrl - q) - kd qdot, clipped to the torque limit.
            act.gaintype = mujoco.mjtGain.mjGAIN_FIXED
            act.biastype = mujoco.mjtBias.mjBIAS_AFFINE
            act.gainprm[0] = j.kp
            act.biasprm[0:3] = [0.0, -j.kp, -j.kd]
            act.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
            act.forcerange = [-j.torque_limit, j.torque_limit]
        for comp, c in self.components.items():
            for body in c.bodies:
                if spec.body(body) is None:
                    raise RobotSpecError(
                        f"robot '{self.name}': components.{comp}: no body '{body}' in {self.mjcf}"
                    )
                sensor = spec.add_sensor(name=f"contact_{body}")
                sensor.type = mujoco.mjtSensor.mjSENS_CONTACT
                sensor.objtype = mujoco.mjtObj.mjOBJ_BODY
                sensor.objname = body
                sensor.intprm[0:3] = [2, 3, 1]  # data="force", reduce="netforce", num=1
        return spec

    def _drop_own_scene(self, spec: mujoco.MjSpec) -> None:
        """Remove the file's actuators, sensors, keyframes and floor planes (see module docstring)."""
        dropped = {
            "<actuator>": list(spec.actuators),
            "<sensor>": list(spec.sensors),
            "<keyframe>": list(spec.keys),
            "floor": [g for g in spec.worldbody.geoms if g.type == mujoco.mjtGeom.mjGEOM_PLANE],
        }
        for elements in dropped.values():
            for e in elements:
                spec.delete(e)
        said = ", ".join(f"{len(v)} {k}" for k, v in dropped.items() if v)
        if said and (self.name, str(self.mjcf)) not in _WARNED:
            _WARNED.add((self.name, str(self.mjcf)))
            log.warning(
                "robot '%s': %s brings its own scene elements (%s): dropped; fallkit adds a PD actuator per "
                "JointSpec, contact sensors per component and its own floor", self.name, self.mjcf, said,
            )  # fmt: skip

    def mj_model(self) -> mujoco.MjModel:
        """The compiled scene: robot with floating base, floor, PD actuators, contact sensors.

        Compiled once per spec; callers that edit the model take a copy first.
        """
        return self._compiled_model

    def model_copy(self, *, update: dict[str, Any] | None = None, deep: bool = False) -> "RobotSpec":
        """A copy with `update`; the compiled model is not carried over (pydantic copies the
        instance dict, cached properties included: a new `mjcf` would keep the old model)."""
        copy = super().model_copy(update=update, deep=deep)
        if update:
            for cached in ("_compiled_model", "_joint_limits", "_mirror"):
                copy.__dict__.pop(cached, None)
        return copy

    @cached_property
    def _compiled_model(self) -> mujoco.MjModel:
        try:
            model = self.mj_spec().compile()
        except RobotSpecError:
            raise
        except Exception as exc:
            raise RobotSpecError(f"robot '{self.name}': mjcf: MuJoCo cannot compile {self.mjcf}: {exc}") from exc
        _check_against_model(self, model)
        return model

    @cached_property
    def _joint_limits(self) -> np.ndarray:
        m = self.mj_model()
        lim = np.array([m.jnt_range[m.joint(n).id] for n in self.joint_names])
        limited = np.array([m.jnt_limited[m.joint(n).id] for n in self.joint_names], bool)
        lim[~limited] = [-np.pi, np.pi]
        return lim

    @property
    def joint_limits(self) -> np.ndarray:
        """[n_joints, 2] lower/upper limits in policy order (±π where unlimited)."""
        return self._joint_limits

    @property
    def mirror_map(self) -> MirrorMap | None:
        """The left–right mirror map (joints, bodies, MuJoCo state), derived from names and checked on the
        model (fallkit.robots.mirror); None when the robot is not mirror-symmetric (`mirror_reason`)."""
        return self._mirror if isinstance(self._mirror, MirrorMap) else None

    @property
    def mirror_reason(self) -> str | None:
        """Why the robot has no mirror map, in one line (None when it has one)."""
        return self._mirror if isinstance(self._mirror, str) else None

    @cached_property
    def _mirror(self) -> MirrorMap | str:
        return derive_mirror(self)

    def nominal_q(self) -> np.ndarray:
        """Nominal pose as a vector in policy order (0 for joints it does not name)."""
        return np.array([self.nominal_pose.get(n, 0.0) for n in self.joint_names])


def _check_against_model(spec: RobotSpec, model: mujoco.MjModel) -> None:
    for name, value in spec.nominal_pose.items():
        jid = model.joint(name).id
        if model.jnt_limited[jid]:
            lo, hi = model.jnt_range[jid]
            if not lo - 1e-9 <= value <= hi + 1e-9:
                raise RobotSpecError(
                    f"robot '{spec.name}': nominal_pose.{name}: {value:.3f} rad is outside "
                    f"the joint range [{lo:.3f}, {hi:.3f}]"
                )
    for j in spec.joints:
        if model.jnt_type[model.joint(j.name).id] != mujoco.mjtJoint.mjJNT_HINGE:
            raise RobotSpecError(f"robot '{spec.name}': joints: '{j.name}' is not a hinge joint")


def make_robot_spec(name: str, **fields) -> RobotSpec:
    """Build a RobotSpec, turning pydantic's errors into one message naming robot and field."""
    try:
        return RobotSpec(name=name, **fields)
    except ValidationError as exc:
        problems = "; ".join(
            f"{'.'.join(str(p) for p in e['loc']) or 'spec'}: {e['msg']}" for e in exc.errors()
        )
        raise RobotSpecError(f"robot '{name}': {problems}") from None
