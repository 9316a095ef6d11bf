"""mujoco_warp backend: N worlds on a GPU (or on Warp's CPU device).

The same scene as the MuJoCo C backend (`RobotSpec.mj_spec()`), the same
`SimState`, the same semantics (see `fallkit.sim.base` and `mujoco_sim.py`):
PD control by the scene's position actuators, per-component contact force from
the scene's native contact sensors (`reduce="netforce"`, computed inside
mujoco_warp's step) recorded at every physics substep, per-world gain scaling
through batched `actuator_gainprm`/`actuator_biasprm`, instability detection and
recovery to the last reset state.

Everything stays on the device: torch tensors are zero-copy views of the Warp
arrays (`wp.to_torch`), and one policy step (substeps x (`mjw.step`, a kernel
recording the contact sensors, a kernel guarding against unstable worlds)) is
captured once as a graph and replayed: a CUDA graph on a GPU, Warp's CPU graph
replay on the CPU (3-5x faster there than launching mujoco_warp's several
hundred kernels per physics step from Python). The only device-to-host transfer
per step is 8 bytes: the overflow flags and the number of unstable worlds.

Unstable worlds are caught after every substep, not only after the policy step as
in the C backend: an exploded world's geometry would otherwise flood the contact
buffer all worlds share, and the other worlds would lose contacts. Either way the
world ends the step at its last reset state, flagged in `SimState.unstable`.

Warp compiles its kernels per model on first use (1-3 minutes on 2 CPU cores);
they are kept in `warp_setup.warp_cache_dir()` (`$FALLKIT_WARP_CACHE`, default
`~/.cache/fallkit/warp`), so later runs load them in seconds. See docs/gpu.md.
"""

from __future__ import annotations

import logging

import mujoco
import numpy as np
import torch
import warp as wp

from fallkit.errors import ConfigError, SimBufferError
from fallkit.robots.spec import RobotSpec
from fallkit.sim.base import Layout, SimState
from fallkit.sim.warp_setup import (
    buffer_overflow_bits,
    capture,
    default_buffers,
    init_warp,
    no_gc,
    overflow_advice,
    preparing_kernels,
    put_warp_model,
    resolve_device,
    use_graphs,
)

log = logging.getLogger(__name__)

# Per-world masses and armature need mujoco_warp's derived constants per world too (set_const over
# batched derived fields), which fallkit has not measured on a GPU yet: refused, not approximated.
_NOT_ON_WARP = "env.randomization.{}: randomised on sim=mujoco only so far; switch it off or use sim=mujoco"


# ---- our own kernels, launched between mujoco_warp's -------------------------------------------
# The guard after every substep and the reset of chosen worlds both put a world back to
# its stored reset state (`_put_back`); `_Worlds` bundles the arrays that takes.


@wp.struct
class _Worlds:
    """The live state of every world and the state each is put back to on a reset, [N, nq] / [N, nv]."""

    qpos: wp.array2d(dtype=float)
    qvel: wp.array2d(dtype=float)
    reset_qpos: wp.array2d(dtype=float)
    reset_qvel: wp.array2d(dtype=float)


@wp.func
def _put_back(w: _Worlds, world: int):
    for i in range(w.qpos.shape[1]):
        w.qpos[world, i] = w.reset_qpos[world, i]
    for i in range(w.qvel.shape[1]):
        w.qvel[world, i] = w.reset_qvel[world, i]


@wp.kernel(enable_backward=False)
def _record_substep(sensordata: wp.array2d(dtype=float), substep: int, out: wp.array3d(dtype=float)):
    world, i = wp.tid()
    out[world, substep, i] = sensordata[world, i]


@wp.kernel(enable_backward=False)
def _guard(max_speed: float, w: _Worlds, qacc_warmstart: wp.array2d(dtype=float), unstable: wp.array(dtype=bool)):
    """After every substep: a world with NaN/Inf or a speed above max_speed is flagged
    and put back to its reset state at once, before the next substep's collision
    detection could see it (an exploded world's geometry would otherwise flood the
    contact buffer that all worlds share)."""
    world = wp.tid()
    ok = bool(True)
    for i in range(w.qpos.shape[1]):
        if not wp.isfinite(w.qpos[world, i]):
            ok = False
    for i in range(w.qvel.shape[1]):
        v = w.qvel[world, i]
        if not wp.isfinite(v) or wp.abs(v) > max_speed:
            ok = False
    if ok:
        return
    unstable[world] = True
    _put_back(w, world)
    for i in range(qacc_warmstart.shape[1]):
        qacc_warmstart[world, i] = 0.0


@wp.kernel(enable_backward=False)
def _restore(mask: wp.array(dtype=bool), w: _Worlds, joint_qpos: wp.array(dtype=int), ctrl: wp.array2d(dtype=float)):
    """Worlds in `mask`: the stored reset state, holding its pose (ctrl = its joint angles)."""
    world = wp.tid()
    if not mask[world]:
        return
    _put_back(w, world)
    for a in range(joint_qpos.shape[0]):  # hold the reset pose
        ctrl[world, a] = w.reset_qpos[world, joint_qpos[a]]


class WarpSim:
    """BatchSim on mujoco_warp. Float32 physics; state tensors live on `device`."""

    def __init__(
        self,
        spec: RobotSpec,
        num_worlds: int,
        device: str = "auto",
        nconmax: int | None = None,
        njmax: int | None = None,
        max_speed: float = 200.0,
        body_state: bool = False,
    ):
        if num_worlds < 1:
            raise ValueError(f"sim: num_worlds must be >= 1, got {num_worlds}")
        init_warp()
        import mujoco_warp as mjw  # once Warp is initialised with fallkit's cache

        self._mjw = mjw
        self.spec = spec
        self.num_worlds = num_worlds
        self.device = torch.device(resolve_device(device))
        self._wp_device = wp.get_device(str(self.device))
        self.substeps = spec.substeps
        self.policy_dt = spec.policy_dt
        self.max_speed = max_speed
        self.num_unstable = 0
        self.body_state = body_state
        self.model = spec.mj_model()
        self.layout = Layout(spec)  # refuses an MJCF with sensors of its own
        default_ncon, default_nj = default_buffers(self.model)
        self.nconmax = nconmax or default_ncon
        self.njmax = njmax or default_nj
        self._buffer_bits = buffer_overflow_bits()

        with preparing_kernels(spec.name, str(self.device)) as self.prepared:  # a machine's first run compiles
            with wp.ScopedDevice(self._wp_device):
                self._put_on_device()
            self._capture_graphs()
        self._state = self._read(torch.zeros(num_worlds, dtype=torch.bool, device=self.device))
        self._write_rows(torch.arange(num_worlds, device=self.device))

    # ---- BatchSim ---------------------------------------------------------------------

    @property
    def state(self) -> SimState:
        return self._state

    def reset(self, world_ids: torch.Tensor, qpos: torch.Tensor, qvel: torch.Tensor) -> None:
        ids = world_ids.to(self.device, torch.long)
        if ids.numel() == 0:
            return
        # checked where the caller made them (the host's sampler: no device read), then copied
        if not bool(torch.isfinite(qpos).all() & torch.isfinite(qvel).all()):
            raise ValueError("sim.reset: qpos/qvel contain NaN or Inf")
        qpos = qpos.detach().to(self.device, torch.float32)
        qvel = qvel.detach().to(self.device, torch.float32)
        self._reset_qpos[ids] = qpos
        self._reset_qvel[ids] = qvel
        self._mask.zero_()
        self._mask[ids] = True
        self._launch_reset()
        self._write_rows(ids)

    def step(self, joint_targets: torch.Tensor) -> SimState:
        self._ctrl.copy_(joint_targets.detach())
        self._qvel_before.copy_(self._qvel)
        with wp.ScopedDevice(self._wp_device):
            if self._step_graph is not None:
                wp.capture_launch(self._step_graph)
            else:
                self._physics_step()
        unstable = self._unstable_flags
        # the one host read per step: buffer overflow anywhere, number of unstable worlds
        flags = torch.stack([(self._overflow & self._buffer_bits).amax().long(), unstable.sum()]).tolist()
        if flags[0]:
            advice = overflow_advice(self._or_bits() & self._buffer_bits, self.nconmax, self.njmax)
            raise SimBufferError(
                f"sim: mujoco_warp buffer overflow ({advice}); contacts were dropped, so this step's physics is wrong"
            )
        state = self._read(unstable)
        self._state = state
        if flags[1]:
            self._recover(unstable)
        return state

    def set_gain_scale(self, scale: torch.Tensor) -> None:
        s = scale.detach().to(self.device, torch.float32).reshape(self.num_worlds, 1)
        self._gainprm[:, :, 0] = self._base_kp * s
        self._biasprm[:, :, 1] = -self._base_kp * s
        self._biasprm[:, :, 2] = -self._base_kd * s

    def set_mass_scale(self, ids: torch.Tensor, scale: torch.Tensor) -> None:
        raise ConfigError(_NOT_ON_WARP.format("mass"))

    def set_joint_scale(self, ids: torch.Tensor, damping: torch.Tensor, armature: torch.Tensor) -> None:
        raise ConfigError(_NOT_ON_WARP.format("joint_damping / armature"))

    def set_friction(self, friction: torch.Tensor) -> None:
        self._geom_friction[:, :, 0] = friction.detach().to(self.device, torch.float32).reshape(-1, 1)

    def set_external_wrench(self, body_ids: torch.Tensor, wrench: torch.Tensor) -> None:
        ids = body_ids.to(self.device, torch.long)
        self._xfrc.zero_()
        self._xfrc[:, ids] = wrench.detach().to(self.device, torch.float32)

    # The physics state that carries over between steps (mjw.Data fields), for exact resume.
    _PHYSICS = ("qpos", "qvel", "act", "qacc_warmstart", "ctrl", "xfrc_applied", "time")

    def state_dict(self) -> dict:
        """Full physics state of every world (warm-start and applied forces included), for exact resume."""
        wp.synchronize_device(self._wp_device)
        physics = {k: wp.to_torch(getattr(self._d, k)).clone() for k in self._PHYSICS}
        return {
            "physics": physics,
            "reset_qpos": self._reset_qpos.clone(),
            "reset_qvel": self._reset_qvel.clone(),
            "gain_scale": self._gainprm[:, :, 0] / self._base_kp,
            "num_unstable": self.num_unstable,
        }

    def load_state_dict(self, state: dict) -> None:
        for k in self._PHYSICS:
            dst = wp.to_torch(getattr(self._d, k))
            src = state["physics"][k]
            if src.shape != dst.shape:
                raise ValueError(f"sim state '{k}' has shape {tuple(src.shape)}, this simulator {tuple(dst.shape)}")
            dst.copy_(src.to(dst.device, dst.dtype))
        self._reset_qpos.copy_(state["reset_qpos"])
        self._reset_qvel.copy_(state["reset_qvel"])
        self.set_gain_scale(state["gain_scale"][:, 0])
        self.num_unstable = int(state["num_unstable"])
        with wp.ScopedDevice(self._wp_device):
            self._mjw.forward(self._m, self._d)
        self._write_rows(torch.arange(self.num_worlds, device=self.device))

    # ---- construction -----------------------------------------------------------------

    def _put_on_device(self) -> None:
        """The device model and data, zero-copy torch views of them, the nominal gains, our own buffers."""
        n, t = self.num_worlds, wp.to_torch
        self._m = put_warp_model(self.model, n, per_world_gains=True)
        d = self._d = self._mjw.put_data(
            self.model, mujoco.MjData(self.model), nworld=n, nconmax=self.nconmax, njmax=self.njmax
        )
        self._qpos, self._qvel, self._ctrl = t(d.qpos), t(d.qvel), t(d.ctrl)
        self._xfrc = t(d.xfrc_applied)  # [N, nbody, 6] force, torque (world)
        self._torque = t(d.actuator_force)
        self._overflow = t(d.overflow)
        self._gainprm = t(self._m.actuator_gainprm)  # [N, nu, 10]
        self._geom_friction = t(self._m.geom_friction)  # [N, ngeom, 3]
        self._biasprm = t(self._m.actuator_biasprm)
        self._base_kp = torch.tensor(self.model.actuator_gainprm[:, 0], dtype=torch.float32, device=self.device)
        self._base_kd = torch.tensor(-self.model.actuator_biasprm[:, 2], dtype=torch.float32, device=self.device)
        self._xpos = t(d.xpos) if self.body_state else None
        self._cvel = t(d.cvel) if self.body_state else None
        # buffers of our own, read by the captured graphs
        self._rec_wp = wp.zeros((n, self.substeps, self.model.nsensordata), dtype=float)
        self._rec = t(self._rec_wp)
        self._mask_wp = wp.zeros(n, dtype=bool)
        self._mask = t(self._mask_wp)
        self._unstable_wp = wp.zeros(n, dtype=bool)
        self._unstable_flags = t(self._unstable_wp)
        self._worlds = _Worlds()
        self._worlds.qpos, self._worlds.qvel = d.qpos, d.qvel
        self._worlds.reset_qpos = wp.array(np.tile(self.model.qpos0, (n, 1)), dtype=float)
        self._worlds.reset_qvel = wp.zeros((n, self.model.nv), dtype=float)
        self._reset_qpos, self._reset_qvel = t(self._worlds.reset_qpos), t(self._worlds.reset_qvel)
        self._joint_qpos_wp = wp.array(self.layout.joint_qpos.numpy().astype(np.int32), dtype=int)
        self._qvel_before = torch.zeros_like(self._qvel)

    def _capture_graphs(self) -> None:
        """Run each sequence once eagerly (compiles/loads every kernel before capture), capture
        both as graphs where Warp can, and leave every world in the model's default state."""
        self._step_graph = self._reset_graph = None
        self._mask.fill_(True)
        with wp.ScopedDevice(self._wp_device):
            self._physics_step()
            self._reset_worlds()
            if not use_graphs(self._wp_device):
                return
            try:
                with no_gc():
                    self._step_graph = capture(self._wp_device, self._physics_step)
                    self._reset_graph = capture(self._wp_device, self._reset_worlds)
            except Exception as exc:  # eager launches are slower, never wrong
                log.warning("sim: Warp graph capture failed on %s (%s); launching kernels one by one",
                            self.device, exc)  # fmt: skip
                self._step_graph = self._reset_graph = None

    # ---- internals --------------------------------------------------------------------

    def _physics_step(self) -> None:
        """One policy step on the device: substeps x (mj_step, record the contact sensors, guard)."""
        mjw, d, n = self._mjw, self._d, self.num_worlds
        self._unstable_wp.zero_()
        for s in range(self.substeps):
            mjw.step(self._m, d)
            wp.launch(_record_substep, dim=(n, self.model.nsensordata), inputs=[d.sensordata, s, self._rec_wp])
            wp.launch(_guard, dim=n, inputs=[self.max_speed, self._worlds, d.qacc_warmstart, self._unstable_wp])

    def _reset_worlds(self) -> None:
        """Worlds in `_mask`: MuJoCo's reset (clears warmstart, forces, time), then the stored reset state."""
        mjw, d = self._mjw, self._d
        mjw.reset_data(self._m, d, reset=self._mask_wp)
        wp.launch(_restore, dim=self.num_worlds, inputs=[self._mask_wp, self._worlds, self._joint_qpos_wp, d.ctrl])
        if self.body_state:  # body poses and velocities of the reset state (the critic reads them)
            mjw.kinematics(self._m, d)
            mjw.com_pos(self._m, d)
            mjw.com_vel(self._m, d)

    def _launch_reset(self) -> None:
        with wp.ScopedDevice(self._wp_device):
            if self._reset_graph is not None:
                wp.capture_launch(self._reset_graph)
            else:
                self._reset_worlds()

    def _or_bits(self) -> int:
        bits = 0
        for b in self._overflow.tolist():
            bits |= int(b)
        return bits

    def _recover(self, unstable: torch.Tensor) -> None:
        """Put unstable worlds back to their last reset state, count and log them."""
        ids = unstable.nonzero().flatten()
        self.num_unstable += len(ids)
        log.warning(
            "sim: %d world(s) became unstable (NaN/Inf or speed > %g) and were reset; %d so far",
            len(ids), self.max_speed, self.num_unstable,
        )
        self._mask.copy_(unstable)
        self._launch_reset()
        self._write_rows(ids)

    def _write_rows(self, ids: torch.Tensor) -> None:
        """Refresh the handed-out state of worlds that were just reset."""
        self.layout.write_rows(
            self._state,
            ids,
            self._qpos[ids],
            self._qvel[ids],
            body_pos=self._xpos[ids] if self.body_state else None,
            body_vel=self._cvel[ids] if self.body_state else None,
        )

    def _read(self, unstable: torch.Tensor) -> SimState:
        """The SimState after a step: clones, since the Warp arrays change with the next step."""
        return self.layout.state(
            qpos=self._qpos.clone(),
            qvel=self._qvel.clone(),
            accel=(self._qvel - self._qvel_before) * (1.0 / self.policy_dt),
            sensordata=self._rec,
            joint_torque=self._torque.clone(),
            unstable=unstable.clone(),
            body_pos=self._xpos.clone() if self.body_state else None,
            body_vel=self._cvel.clone() if self.body_state else None,
        )
