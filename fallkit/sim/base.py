"""The BatchSim interface: N worlds of one robot, stepped together.

Every backend (MuJoCo C on CPU threads, mujoco_warp on a GPU) builds the same
scene from `RobotSpec.mj_spec()` and exposes the same `SimState` of torch
tensors on its device, so the environment, the samplers and the evaluation
never know which backend runs.

Conventions (world frame: z up; quaternions w, x, y, z; joints in policy order):
  root_lin_vel   world frame [m/s]
  root_ang_vel   root (body) frame [rad/s], as MuJoCo's free joint stores it
  root_lin_acc   world frame [m/s^2], (v_end - v_start) / policy_dt: the kinematic
                 acceleration, gravity not subtracted (free fall reads 9.81 m/s^2
                 downward; an accelerometer would read 0)
  joint_acc      (qdot_end - qdot_start) / policy_dt [rad/s^2]
  joint_torque   actuator torque at the last physics substep [N·m]
  contact_force  [N, substeps, components, 3] net contact force on each component
                 at each physics substep of the last policy step, world frame [N],
                 the force the component receives (resting: +weight along z).
                 A record describes the state at the start of its substep, as
                 MuJoCo's derived quantities do after mj_step.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Protocol

import mujoco
import numpy as np
import torch

from fallkit.robots.spec import RobotSpec


@dataclass
class SimState:
    """State of all worlds after the last reset or step; tensors on the sim's device."""

    qpos: torch.Tensor  # [N, nq] MuJoCo layout: root xyz, root quat, joints in MJCF order
    qvel: torch.Tensor  # [N, nv]
    root_pos: torch.Tensor  # [N, 3]
    root_quat: torch.Tensor  # [N, 4]
    root_lin_vel: torch.Tensor  # [N, 3] world frame
    root_ang_vel: torch.Tensor  # [N, 3] root frame
    root_lin_acc: torch.Tensor  # [N, 3] world frame
    joint_pos: torch.Tensor  # [N, J] policy order
    joint_vel: torch.Tensor  # [N, J]
    joint_acc: torch.Tensor  # [N, J]
    joint_torque: torch.Tensor  # [N, J]
    contact_force: torch.Tensor  # [N, S, C, 3]
    unstable: torch.Tensor  # [N] bool: found unstable in the last step, and reset
    # Only with body_state=True (the critic's privileged observation), else None:
    body_pos: torch.Tensor | None = None  # [N, B, 3] world positions of all bodies (0 = world)
    body_vel: torch.Tensor | None = None  # [N, B, 6] MuJoCo cvel: angular, linear about the subtree CoM

    def clone(self) -> "SimState":
        return SimState(**{f.name: _clone(getattr(self, f.name)) for f in fields(self)})

    def contact_force_norm(self) -> torch.Tensor:
        """|f_c| [N, S, C]: the magnitude of each component's contact force at each substep [N]."""
        return self.contact_force.norm(dim=-1)

    def peak_contact_force(self) -> torch.Tensor:
        """[N, C]: the largest |f_c| on each component over the physics substeps of the last step [N]."""
        return self.contact_force_norm().amax(dim=1)


def _clone(t: torch.Tensor | None) -> torch.Tensor | None:
    return None if t is None else t.clone()


class BatchSim(Protocol):
    """What every simulator backend provides."""

    spec: RobotSpec
    num_worlds: int
    device: torch.device
    substeps: int
    num_unstable: int  # worlds found unstable and reset since construction
    layout: Layout  # index maps between MuJoCo's layout and policy order

    @property
    def state(self) -> SimState: ...

    def reset(self, world_ids: torch.Tensor, qpos: torch.Tensor, qvel: torch.Tensor) -> None:
        """Put worlds `world_ids` into the given MuJoCo-layout states (forward kinematics included)."""

    def step(self, joint_targets: torch.Tensor) -> SimState:
        """One policy step: `substeps` physics steps of PD control toward `joint_targets` [N, J]."""

    def set_gain_scale(self, scale: torch.Tensor) -> None:
        """Scale kp and kd of every actuator, per world ([N]); 0 = zero torque."""

    def set_external_wrench(self, body_ids: torch.Tensor, wrench: torch.Tensor) -> None:
        """Apply [N, len(body_ids), 6] force (xyz) and torque (xyz), world frame, until changed."""

    def set_friction(self, friction: torch.Tensor) -> None:
        """Sliding friction of every geom, per world ([N]): every contact's coefficient (MuJoCo
        takes the larger of the two geoms'), until changed."""

    def set_mass_scale(self, ids: torch.Tensor, scale: torch.Tensor) -> None:
        """Worlds `ids`: every body's mass and rotational inertia = the model's × scale [len(ids), nbody],
        with the constants MuJoCo derives from them (mj_setConst) recomputed, until changed."""

    def set_joint_scale(self, ids: torch.Tensor, damping: torch.Tensor, armature: torch.Tensor) -> None:
        """Worlds `ids`: every dof's viscous damping and armature = the model's × damping, armature
        [len(ids)] (armature with mj_setConst's derived constants), until changed."""

    def state_dict(self) -> dict:
        """The full physics state of all worlds, so a resumed run continues exactly."""

    def load_state_dict(self, state: dict) -> None:
        """Restore what state_dict() returned."""


@dataclass
class _Indices:
    joint_qpos: torch.Tensor
    joint_qvel: torch.Tensor
    sensor_order: torch.Tensor
    neg_component_sum: torch.Tensor


class Layout:
    """Index maps between MuJoCo's layout and policy order, shared by the backends."""

    def __init__(self, spec: RobotSpec):
        m = spec.mj_model()
        self.nq, self.nv, self.nbody = m.nq, m.nv, m.nbody
        root = m.body(spec.root_body)
        jid = m.body_jntadr[root.id]
        if m.jnt_type[jid] != mujoco.mjtJoint.mjJNT_FREE:
            raise ValueError(f"robot '{spec.name}': root body '{spec.root_body}' has no free joint")
        self.root_qpos = int(m.jnt_qposadr[jid])
        self.root_qvel = int(m.jnt_dofadr[jid])
        self.root_body = int(root.id)
        self.joint_qpos = torch.tensor([m.jnt_qposadr[m.joint(n).id] for n in spec.joint_names])
        self.joint_qvel = torch.tensor([m.jnt_dofadr[m.joint(n).id] for n in spec.joint_names])
        # contact sensors are added per component body, in component order
        comp_of_sensor, sensor_adr = [], []
        for c, comp in enumerate(spec.components.values()):
            for body in comp.bodies:
                s = m.sensor(f"contact_{body}")
                comp_of_sensor.append(c)
                sensor_adr.append(int(m.sensor_adr[s.id]))
        self.sensor_adr = torch.tensor(sensor_adr)
        # [C, bodies] 0/1 matrix summing body sensors into components
        self.component_sum = torch.zeros(len(spec.components), len(sensor_adr))
        self.component_sum[comp_of_sensor, torch.arange(len(sensor_adr))] = 1.0
        self.qpos0 = torch.tensor(m.qpos0, dtype=torch.float64)
        if m.nsensordata != 3 * len(sensor_adr):
            raise ValueError(f"robot '{spec.name}': the MJCF must not define sensors of its own")
        self._on: dict[str, _Indices] = {}

    def on(self, device: torch.device) -> "_Indices":
        """The index tensors on `device` (cached: backends call this every step)."""
        key = str(device)
        if key not in self._on:
            self._on[key] = _Indices(
                joint_qpos=self.joint_qpos.to(device),
                joint_qvel=self.joint_qvel.to(device),
                sensor_order=(self.sensor_adr // 3).long().to(device),
                neg_component_sum=(-self.component_sum).to(device),
            )
        return self._on[key]

    def state(
        self,
        qpos: torch.Tensor,
        qvel: torch.Tensor,
        accel: torch.Tensor,
        sensordata: torch.Tensor,
        joint_torque: torch.Tensor,
        unstable: torch.Tensor,
        body_pos: torch.Tensor | None,
        body_vel: torch.Tensor | None,
    ) -> SimState:
        """A SimState from a backend's float32 tensors (one device): the slicing every backend shares.

        qpos/qvel [N, nq/nv]; accel = Δqvel / policy_dt [N, nv]; sensordata [N, S, nsensordata]
        holds the contact sensors of every substep (the scene has no other sensors).
        """
        idx = self.on(qpos.device)
        n, s = sensordata.shape[:2]
        # body sensors [N, S, bodies, 3] summed into components; MuJoCo reports the
        # force the body exerts, so the sign flips to the force the component receives.
        body_f = sensordata.view(n, s, -1, 3)[:, :, idx.sensor_order]
        r, v = self.root_qpos, self.root_qvel
        return SimState(
            qpos=qpos,
            qvel=qvel,
            root_pos=qpos[:, r : r + 3],
            root_quat=qpos[:, r + 3 : r + 7],
            root_lin_vel=qvel[:, v : v + 3],
            root_ang_vel=qvel[:, v + 3 : v + 6],
            root_lin_acc=accel[:, v : v + 3],
            joint_pos=qpos[:, idx.joint_qpos],
            joint_vel=qvel[:, idx.joint_qvel],
            joint_acc=accel[:, idx.joint_qvel],
            joint_torque=joint_torque,
            contact_force=torch.einsum("cb,nsbk->nsck", idx.neg_component_sum, body_f),
            unstable=unstable,
            body_pos=body_pos,
            body_vel=body_vel,
        )

    def write_rows(
        self,
        state: SimState,
        ids: torch.Tensor | np.ndarray,
        qpos: torch.Tensor,
        qvel: torch.Tensor,
        body_pos: torch.Tensor | None = None,
        body_vel: torch.Tensor | None = None,
    ) -> None:
        """Refresh the handed-out `state` of worlds `ids` that were just reset.

        qpos/qvel [len(ids), nq/nv] (and body_pos/body_vel when the sim keeps body state)
        are those worlds' float32 rows on the state's device; the quantities a step
        measures (accelerations, torques, contact forces) become 0.
        """
        st, idx = state, self.on(state.qpos.device)
        st.qpos[ids] = qpos
        st.qvel[ids] = qvel
        r, v = self.root_qpos, self.root_qvel
        st.root_pos[ids] = st.qpos[ids, r : r + 3]
        st.root_quat[ids] = st.qpos[ids, r + 3 : r + 7]
        st.root_lin_vel[ids] = st.qvel[ids, v : v + 3]
        st.root_ang_vel[ids] = st.qvel[ids, v + 3 : v + 6]
        st.joint_pos[ids] = st.qpos[ids][:, idx.joint_qpos]
        st.joint_vel[ids] = st.qvel[ids][:, idx.joint_qvel]
        if body_pos is not None:
            st.body_pos[ids] = body_pos
            st.body_vel[ids] = body_vel
        for name in ("root_lin_acc", "joint_acc", "joint_torque", "contact_force"):
            getattr(st, name)[ids] = 0.0

    def qpos(
        self, root_pos: torch.Tensor, root_quat: torch.Tensor, joint_pos: torch.Tensor
    ) -> torch.Tensor:
        """MuJoCo-layout qpos [n, nq] from root pose and joint angles in policy order."""
        n = root_pos.shape[0]
        q = self.qpos0.to(root_pos.dtype).repeat(n, 1)
        q[:, self.root_qpos : self.root_qpos + 3] = root_pos
        q[:, self.root_qpos + 3 : self.root_qpos + 7] = root_quat
        q[:, self.joint_qpos] = joint_pos.to(q.dtype)
        return q

    def qvel(
        self, root_lin_vel: torch.Tensor, root_ang_vel: torch.Tensor, joint_vel: torch.Tensor
    ) -> torch.Tensor:
        """MuJoCo-layout qvel [n, nv]; root_lin_vel in world, root_ang_vel in root frame."""
        n = root_lin_vel.shape[0]
        v = torch.zeros(n, self.nv, dtype=root_lin_vel.dtype)
        v[:, self.root_qvel : self.root_qvel + 3] = root_lin_vel
        v[:, self.root_qvel + 3 : self.root_qvel + 6] = root_ang_vel
        v[:, self.joint_qvel] = joint_vel.to(v.dtype)
        return v
