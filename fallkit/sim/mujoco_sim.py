"""MuJoCo C backend: N worlds on a persistent thread pool (`mujoco.batch.Batch`).

One policy step is one `Batch.rollout` call of `substeps` physics steps that
records the contact sensors after every substep, so PD control (MuJoCo position
actuators) and the per-component contact forces are all computed in C, on all
threads, with no Python per substep.
"""

from __future__ import annotations

import logging

import mujoco
import mujoco.batch
import numpy as np
import torch

from fallkit.machine import core_share
from fallkit.robots.spec import RobotSpec
from fallkit.sim.base import Layout, SimState

log = logging.getLogger(__name__)


class MujocoSim:
    """BatchSim on MuJoCo C. Float64 physics; state handed out as float32 torch tensors."""

    def __init__(
        self,
        spec: RobotSpec,
        num_worlds: int,
        threads: int = 0,
        max_speed: float = 200.0,
        body_state: bool = False,
    ):
        if num_worlds < 1:
            raise ValueError(f"sim: num_worlds must be >= 1, got {num_worlds}")
        self.spec = spec
        self.num_worlds = num_worlds
        self.device = torch.device("cpu")
        self.substeps = spec.substeps
        self.policy_dt = spec.policy_dt
        self.max_speed = max_speed
        self.num_unstable = 0
        self.model = spec.mj_model()
        self.layout = Layout(spec)
        # threads=0: this process's share of the cores (fallkit.machine), not every core
        self.batch = mujoco.batch.Batch(self.model, num_worlds, nthread=threads or core_share())

        b = self.batch
        self._qpos, self._qvel, self._ctrl = b.bind("qpos"), b.bind("qvel"), b.bind("ctrl")
        self._xfrc = b.bind("xfrc_applied")
        # derived outputs, refreshed by every call (one substep behind after a step);
        # body kinematics cost ~5 % of the physics, so only when asked for (critic)
        self.body_state = body_state
        self._xpos = b.bind("xpos") if body_state else None
        self._cvel = b.bind("cvel") if body_state else None
        self._torque = b.bind("actuator_force")
        self._warning = b.warning
        self._friction: np.ndarray | None = None  # per-world geom friction, once randomised
        self._mass = self._inertia = self._damping = self._armature = None  # per world, once randomised
        self._base_kp = self.model.actuator_gainprm[:, 0].copy()
        self._base_kd = -self.model.actuator_biasprm[:, 2].copy()
        self._gainprm = None  # expanded per world on first gain change (shared until then)
        # only the contact sensors are needed at every substep
        self._rec = {"sensordata": np.zeros((num_worlds, self.substeps, self.model.nsensordata))}

        # Every world starts in the model's default state (qpos0, at rest).
        b.reset()
        self._reset_qpos = self._qpos.copy()
        self._reset_qvel = self._qvel.copy()
        self._state = self._read(
            np.zeros((num_worlds, self.substeps, self.model.nsensordata)),
            np.zeros((num_worlds, self.model.nu)),
            self._qvel.copy(),
            np.zeros(num_worlds, bool),
        )

    # ---- BatchSim ---------------------------------------------------------------------

    @property
    def state(self) -> SimState:
        return self._state

    def reset(self, world_ids: torch.Tensor, qpos: torch.Tensor, qvel: torch.Tensor) -> None:
        ids = np.asarray(world_ids.cpu(), dtype=np.int64)
        if ids.size == 0:
            return
        qpos = np.asarray(qpos.detach().cpu(), dtype=np.float64)
        qvel = np.asarray(qvel.detach().cpu(), dtype=np.float64)
        if not (np.isfinite(qpos).all() and np.isfinite(qvel).all()):
            raise ValueError("sim.reset: qpos/qvel contain NaN or Inf")
        self._reset_qpos[ids] = qpos
        self._reset_qvel[ids] = qvel
        self._restart(ids, qpos, qvel)

    def step(self, joint_targets: torch.Tensor) -> SimState:
        targets = np.asarray(joint_targets.detach().cpu(), dtype=np.float64)
        self._ctrl[:] = targets
        qvel_before = self._qvel.copy()
        warnings_before = self._warning[:, :, 1].sum(axis=-1).copy()
        failed = np.zeros(self.num_worlds, bool)
        try:
            self.batch.rollout(self.substeps, record=tuple(self._rec), out=self._rec)
        except mujoco.batch.SimulationError as exc:
            failed[np.asarray(exc.args[0], dtype=np.int64)] = True
        unstable = failed | self._unstable(warnings_before)
        state = self._read(self._rec["sensordata"], self._torque, qvel_before, unstable)
        self._state = state
        if unstable.any():
            self._recover(np.flatnonzero(unstable))
        return state

    def set_gain_scale(self, scale: torch.Tensor) -> None:
        s = np.asarray(scale.detach().cpu(), dtype=np.float64).reshape(self.num_worlds, 1)
        if self._gainprm is None:
            self._gainprm = self.batch.expand("actuator_gainprm")
            self._biasprm = self.batch.expand("actuator_biasprm")
        self._gainprm[:, :, 0] = self._base_kp * s
        self._biasprm[:, :, 1] = -self._base_kp * s
        self._biasprm[:, :, 2] = -self._base_kd * s

    def set_mass_scale(self, ids: torch.Tensor, scale: torch.Tensor) -> None:
        if self._mass is None:  # per world from now on
            self._mass, self._inertia = self.batch.expand("body_mass"), self.batch.expand("body_inertia")
        rows, s = _rows(ids), np.asarray(scale.detach().cpu(), dtype=np.float64)
        self._mass[rows] = self.model.body_mass * s
        self._inertia[rows] = self.model.body_inertia * s[..., None]
        self.batch.set_const(rows)  # inverse weights, subtree masses … follow the new masses

    def set_joint_scale(self, ids: torch.Tensor, damping: torch.Tensor, armature: torch.Tensor) -> None:
        if self._damping is None:
            self._damping, self._armature = self.batch.expand("dof_damping"), self.batch.expand("dof_armature")
        rows = _rows(ids)
        self._damping[rows] = self.model.dof_damping * np.asarray(damping.detach().cpu(), np.float64)[:, None]
        self._armature[rows] = self.model.dof_armature * np.asarray(armature.detach().cpu(), np.float64)[:, None]
        self.batch.set_const(rows)  # armature enters the derived inverse weights

    def set_friction(self, friction: torch.Tensor) -> None:
        if self._friction is None:
            self._friction = self.batch.expand("geom_friction")  # [N, ngeom, 3], per world from now on
        self._friction[:, :, 0] = np.asarray(friction.detach().cpu(), dtype=np.float64).reshape(-1, 1)

    def set_external_wrench(self, body_ids: torch.Tensor, wrench: torch.Tensor) -> None:
        ids = np.asarray(body_ids.cpu(), dtype=np.int64)
        self._xfrc[:] = 0.0
        self._xfrc[:, ids] = np.asarray(wrench.detach().cpu(), dtype=np.float64)

    def state_dict(self) -> dict:
        """Full physics state of every world (warm-start and applied forces included), for exact resume."""
        return {
            "physics": torch.from_numpy(self.batch.state.copy()),
            "reset_qpos": torch.from_numpy(self._reset_qpos.copy()),
            "reset_qvel": torch.from_numpy(self._reset_qvel.copy()),
            "gain_scale": None if self._gainprm is None else torch.from_numpy(self._gainprm[:, :, 0] / self._base_kp),
            "num_unstable": self.num_unstable,
        }

    def load_state_dict(self, state: dict) -> None:
        physics = state["physics"].numpy()
        if physics.shape != self.batch.state.shape:
            raise ValueError(f"sim state has shape {physics.shape}, this simulator {self.batch.state.shape}")
        self.batch.state[:] = physics
        self._reset_qpos[:] = state["reset_qpos"].numpy()
        self._reset_qvel[:] = state["reset_qvel"].numpy()
        if state["gain_scale"] is not None:
            self.set_gain_scale(state["gain_scale"][:, 0])
        self.num_unstable = int(state["num_unstable"])
        self.batch.forward()
        self._write_rows(np.arange(self.num_worlds))

    # ---- internals --------------------------------------------------------------------

    def _unstable(self, warnings_before: np.ndarray) -> np.ndarray:
        qpos, qvel = self._qpos, self._qvel
        bad = ~np.isfinite(qpos).all(axis=1) | ~np.isfinite(qvel).all(axis=1)
        bad |= np.abs(qvel).max(axis=1) > self.max_speed
        # MuJoCo resets a diverging world itself (mj_checkAcc) and raises a warning
        bad |= self._warning[:, :, 1].sum(axis=-1) > warnings_before
        return bad

    def _recover(self, ids: np.ndarray) -> None:
        """Put unstable worlds back to their last reset state, count and log them."""
        self.num_unstable += len(ids)
        log.warning(
            "sim: %d world(s) became unstable (NaN/Inf, speed > %g, or a MuJoCo warning) and were reset; "
            "%d so far", len(ids), self.max_speed, self.num_unstable,
        )
        self._restart(ids, self._reset_qpos[ids].copy(), self._reset_qvel[ids].copy())

    def _restart(self, ids: np.ndarray, qpos: np.ndarray, qvel: np.ndarray) -> None:
        """MuJoCo's reset of worlds `ids` (warm start, forces, time), then these states, holding their pose."""
        # Batch.reset discards writes made before it, so reset first, then write.
        self.batch.reset(ids, stage=mujoco.mjtStage.mjSTAGE_NONE)
        self._qpos[ids] = qpos
        self._qvel[ids] = qvel
        self._ctrl[ids] = qpos[:, self.layout.joint_qpos.numpy()]  # hold the reset pose
        self.batch.forward(ids)
        self._write_rows(ids)

    def _write_rows(self, ids: np.ndarray) -> None:
        """Refresh the handed-out state of worlds that were just reset."""
        self.layout.write_rows(
            self._state,
            ids,
            torch.from_numpy(self._qpos[ids]).float(),
            torch.from_numpy(self._qvel[ids]).float(),
            body_pos=torch.tensor(self._xpos[ids], dtype=torch.float32) if self.body_state else None,
            body_vel=torch.tensor(self._cvel[ids], dtype=torch.float32) if self.body_state else None,
        )

    def _read(self, sensordata: np.ndarray, torque: np.ndarray, qvel_before: np.ndarray, unstable: np.ndarray) -> SimState:
        qvel64 = torch.from_numpy(self._qvel)
        accel = ((qvel64 - torch.from_numpy(qvel_before)) * (1.0 / self.policy_dt)).float()
        return self.layout.state(
            qpos=torch.from_numpy(self._qpos).float(),
            qvel=qvel64.float(),
            accel=accel,
            sensordata=torch.from_numpy(sensordata).float(),
            joint_torque=torch.tensor(torque, dtype=torch.float32),  # outputs are read-only
            unstable=torch.from_numpy(unstable.copy()),
            body_pos=torch.tensor(self._xpos, dtype=torch.float32) if self.body_state else None,
            body_vel=torch.tensor(self._cvel, dtype=torch.float32) if self.body_state else None,
        )


def _rows(ids: torch.Tensor) -> np.ndarray:
    return np.asarray(ids.detach().cpu(), dtype=np.int64)
