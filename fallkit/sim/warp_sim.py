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
they are kept in `warp_cache_dir()` (`$FALLKIT_WARP_CACHE`, default
`~/.cache/fallkit/warp`), so later runs load them in seconds. See docs/gpu.md.
"""

from __future__ import annotations

import gc
import logging
import math
import os
import re
from contextlib import contextmanager
from pathlib import Path

import mujoco
import numpy as np
import torch
import warp as wp

from fallkit.errors import ConfigError, SimBufferError
from fallkit.robots.spec import RobotSpec
from fallkit.sim.base import Layout, SimState

log = logging.getLogger(__name__)

_warp_ready = False


def warp_cache_dir() -> Path:
    """Where Warp's compiled kernels are kept: $FALLKIT_WARP_CACHE or ~/.cache/fallkit/warp."""
    return Path(os.environ.get("FALLKIT_WARP_CACHE") or Path.home() / ".cache" / "fallkit" / "warp").expanduser()


def init_warp():
    """Import and initialise Warp once, with fallkit's kernel cache and quiet logging.

    Returns the `warp` module. Every fallkit code path that touches Warp calls this
    first, so the kernels always land in the same cache.
    """
    global _warp_ready
    if not _warp_ready:
        path = str(warp_cache_dir())
        wp.config.kernel_cache_dir = path
        wp.config.log_level = wp.LOG_WARNING  # no greeting, no per-module load lines
        if wp._src.context.runtime is None:
            wp.init()
        else:  # someone initialised Warp before us: move its cache here
            wp._src.build.init_kernel_cache(path)
        _warp_ready = True
    return wp


def resolve_device(device: str) -> str:
    """'auto' | 'cpu' | 'cuda' | 'cuda:N' -> a Warp/torch device string, or a ConfigError."""
    init_warp()
    if device == "auto":
        return "cuda:0" if torch.cuda.is_available() and wp.is_cuda_available() else "cpu"
    if device == "cpu":
        return "cpu"
    m = re.fullmatch(r"cuda(?::(\d+))?", device)
    if m is None:
        raise ConfigError(f"sim.device: expected auto, cpu or cuda:N, got '{device}'")
    if not (torch.cuda.is_available() and wp.is_cuda_available()):
        why = "Warp finds no CUDA driver" if torch.cuda.is_available() else "torch has no CUDA (CPU build of torch?)"
        raise ConfigError(
            f"sim.device: '{device}' requested but no CUDA device is usable ({why}); use sim.device=cpu or auto"
        )
    index = int(m.group(1) or 0)
    if index >= torch.cuda.device_count():
        raise ConfigError(f"sim.device: '{device}' requested but only {torch.cuda.device_count()} CUDA device(s) exist")
    return f"cuda:{index}"


# Most contacts one geom of each type can make with a plane (MuJoCo's plane colliders).
_PLANE_CONTACTS = {
    int(mujoco.mjtGeom.mjGEOM_SPHERE): 1,
    int(mujoco.mjtGeom.mjGEOM_ELLIPSOID): 1,
    int(mujoco.mjtGeom.mjGEOM_CAPSULE): 2,
}


def default_buffers(model: mujoco.MjModel) -> tuple[int, int]:
    """(nconmax, njmax) for a robot lying on the floor, from its collision geometry.

    nconmax (contacts per world, pooled over all worlds): half of the contacts all
    robot geoms could make with the floor at once (1 per sphere, 2 per capsule, 4 per
    box, cylinder or mesh; a lying robot touches with at most about half of them, and
    self-contacts take the rest), at least 16, in multiples of 8.
    njmax (constraint rows per world, a hard per-world limit): every such contact
    takes 2(condim-1) rows with pyramidal friction cones (4 for condim 3), plus one
    row per limited joint and per equality row. biped20: 48 and 212, against at most
    14 contacts / 56 rows seen in 200 simulated falls with MuJoCo C.
    """
    floor = [g for g in range(model.ngeom) if model.geom_bodyid[g] == 0]
    robot = [g for g in range(model.ngeom) if model.geom_bodyid[g] != 0]

    def touches_floor(g: int) -> bool:
        return any(
            (model.geom_contype[g] & model.geom_conaffinity[f]) or (model.geom_contype[f] & model.geom_conaffinity[g])
            for f in floor
        )

    plane = sum(_PLANE_CONTACTS.get(int(model.geom_type[g]), 4) for g in robot if touches_floor(g))
    nconmax = max(16, 8 * math.ceil(plane / 2 / 8))
    condim = int(model.geom_condim.max()) if model.ngeom else 3
    if model.opt.cone == mujoco.mjtCone.mjCONE_PYRAMIDAL:
        rows = 1 if condim == 1 else 2 * (condim - 1)
    else:
        rows = condim
    eq_rows = {0: 3, 1: 6, 2: 1, 3: 1, 4: 1}  # connect, weld, joint, tendon, flex
    neq_rows = sum(eq_rows.get(int(t), 6) for t in model.eq_type)
    njmax = rows * nconmax + int(model.jnt_limited.sum()) + int(model.tendon_limited.sum()) + neq_rows
    njmax += int((model.dof_frictionloss > 0).sum())
    return nconmax, njmax


# mujoco_warp's overflow bits that mean dropped contacts/constraints -> which setting to raise.
def _overflow_advice(bits: int, nconmax: int, njmax: int) -> str:
    from mujoco_warp import OverflowType as O

    advice = []
    if bits & (O.NEFC | O.NJMAX_NNZ):
        advice.append(f"a world needed more than sim.njmax={njmax} constraint rows: raise sim.njmax")
    if bits & (O.BROADPHASE | O.NARROWPHASE | O.CCD):
        advice.append(
            f"the worlds made more than sim.nconmax={nconmax} contacts per world on average: raise sim.nconmax"
        )
    if bits & O.CONTACT_MATCH:
        advice.append("a component body touched more contacts than mujoco_warp's contact_sensor_maxmatch (64)")
    other = bits & ~(O.NEFC | O.NJMAX_NNZ | O.BROADPHASE | O.NARROWPHASE | O.CCD | O.CONTACT_MATCH)
    if other:
        advice.append(f"mujoco_warp overflow {O(other)!r}")
    return "; ".join(advice)


def put_warp_model(model: mujoco.MjModel, num_worlds: int, per_world_gains: bool):
    """The device model, as both fallkit and the raw benchmark build it (same kernels)."""
    import mujoco_warp as mjw

    batch = {"actuator_gainprm": num_worlds, "actuator_biasprm": num_worlds} if per_world_gains else None
    m = mjw.put_model(model, batch_sizes=batch)
    # fallkit checks the overflow flags itself and raises one clear error, so the
    # kernels' own printf warnings (also printed for solver iteration limits) stay off.
    m.opt.warn_overflow = 0
    return m


def use_graphs(device) -> bool:
    """Capture graphs where Warp can: always on the CPU (Warp's CPU graph replay); on
    CUDA with a memory pool (mujoco_warp allocates inside its step) and conditional
    graph nodes (driver and toolkit >= 12.4: the solver loop is a `capture_while`)."""
    init_warp()
    if device.is_cpu:
        return True
    return bool(wp.is_mempool_enabled(device)) and wp.is_conditional_graph_supported()


@contextmanager
def _no_gc():
    # a stale Warp graph finalised during capture would record its destructor into the new graph
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()


@wp.kernel(enable_backward=False)
def _record_substep(sensordata: wp.array2d(dtype=float), substep: int, out: wp.array3d(dtype=float)):
    world, i = wp.tid()
    out[world, substep, i] = sensordata[world, i]


@wp.kernel(enable_backward=False)
def _guard(
    max_speed: float,
    reset_qpos: wp.array2d(dtype=float),
    reset_qvel: wp.array2d(dtype=float),
    qpos: wp.array2d(dtype=float),
    qvel: wp.array2d(dtype=float),
    qacc_warmstart: wp.array2d(dtype=float),
    unstable: wp.array(dtype=bool),
):
    """After every substep: a world with NaN/Inf or a speed above max_speed is flagged
    and put back to its reset state at once, before the next substep's collision
    detection could see it (an exploded world's geometry would otherwise flood the
    contact buffer that all worlds share)."""
    world = wp.tid()
    ok = bool(True)
    for i in range(qpos.shape[1]):
        if not wp.isfinite(qpos[world, i]):
            ok = False
    for i in range(qvel.shape[1]):
        v = qvel[world, i]
        if not wp.isfinite(v) or wp.abs(v) > max_speed:
            ok = False
    if ok:
        return
    unstable[world] = True
    for i in range(qpos.shape[1]):
        qpos[world, i] = reset_qpos[world, i]
    for i in range(qvel.shape[1]):
        qvel[world, i] = reset_qvel[world, i]
        qacc_warmstart[world, i] = 0.0


@wp.kernel(enable_backward=False)
def _restore(
    mask: wp.array(dtype=bool),
    reset_qpos: wp.array2d(dtype=float),
    reset_qvel: wp.array2d(dtype=float),
    joint_qpos: wp.array(dtype=int),
    qpos: wp.array2d(dtype=float),
    qvel: wp.array2d(dtype=float),
    ctrl: wp.array2d(dtype=float),
):
    world = wp.tid()
    if not mask[world]:
        return
    for i in range(reset_qpos.shape[1]):
        qpos[world, i] = reset_qpos[world, i]
    for i in range(reset_qvel.shape[1]):
        qvel[world, i] = reset_qvel[world, i]
    for a in range(joint_qpos.shape[0]):  # hold the reset pose
        ctrl[world, a] = reset_qpos[world, joint_qpos[a]]


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
        import mujoco_warp as mjw

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
        self.layout = Layout(spec)
        if self.model.nsensordata != 3 * len(self.layout.sensor_adr):
            raise ValueError(f"robot '{spec.name}': the MJCF must not define sensors of its own")
        default_ncon, default_nj = default_buffers(self.model)
        self.nconmax = nconmax or default_ncon
        self.njmax = njmax or default_nj

        n, dev = num_worlds, self.device
        with wp.ScopedDevice(self._wp_device):
            self._m = put_warp_model(self.model, n, per_world_gains=True)
            self._d = mjw.put_data(
                self.model, mujoco.MjData(self.model), nworld=n, nconmax=self.nconmax, njmax=self.njmax
            )
            d = self._d
            # zero-copy torch views of the Warp arrays
            t = wp.to_torch
            self._qpos, self._qvel, self._ctrl = t(d.qpos), t(d.qvel), t(d.ctrl)
            self._xfrc = t(d.xfrc_applied)  # [N, nbody, 6] force, torque (world)
            self._torque = t(d.actuator_force)
            self._overflow = t(d.overflow)
            self._gainprm = t(self._m.actuator_gainprm)  # [N, nu, 10]
            self._biasprm = t(self._m.actuator_biasprm)
            self._xpos = t(d.xpos) if body_state else None
            self._cvel = t(d.cvel) if body_state else None
            # buffers of our own, read by the captured graphs
            self._rec_wp = wp.zeros((n, self.substeps, self.model.nsensordata), dtype=float)
            self._rec = t(self._rec_wp)
            self._mask_wp = wp.zeros(n, dtype=bool)
            self._mask = t(self._mask_wp)
            self._unstable_wp = wp.zeros(n, dtype=bool)
            self._unstable_flags = t(self._unstable_wp)
            self._reset_qpos_wp = wp.array(np.tile(self.model.qpos0, (n, 1)), dtype=float)
            self._reset_qvel_wp = wp.zeros((n, self.model.nv), dtype=float)
            self._reset_qpos, self._reset_qvel = t(self._reset_qpos_wp), t(self._reset_qvel_wp)
            self._joint_qpos_wp = wp.array(self.layout.joint_qpos.numpy().astype(np.int32), dtype=int)

        self._base_kp = torch.tensor(self.model.actuator_gainprm[:, 0], dtype=torch.float32, device=dev)
        self._base_kd = torch.tensor(-self.model.actuator_biasprm[:, 2], dtype=torch.float32, device=dev)
        self._joint_qpos = self.layout.joint_qpos.to(dev)
        self._joint_qvel = self.layout.joint_qvel.to(dev)
        self._qvel_before = torch.zeros_like(self._qvel)
        # overflows that drop contacts or constraint rows (not the solver's iteration
        # limits, nor EPA's polytope size, which only cost accuracy, as in MuJoCo C)
        O = mjw.OverflowType
        self._buffer_bits = int(O.NEFC | O.NJMAX_NNZ | O.BROADPHASE | O.NARROWPHASE | O.CCD | O.CONTACT_MATCH | O.NVMAX)

        # Run each sequence once eagerly (compiles/loads every kernel before capture),
        # then put every world back into the model's default state (qpos0, at rest).
        self._step_graph = self._reset_graph = None
        self._mask.fill_(True)
        with wp.ScopedDevice(self._wp_device):
            self._physics_step()
            self._reset_worlds()
            if use_graphs(self._wp_device):
                try:
                    with _no_gc():
                        with wp.ScopedCapture(device=self._wp_device) as cap:
                            self._physics_step()
                        self._step_graph = cap.graph
                        with wp.ScopedCapture(device=self._wp_device) as cap:
                            self._reset_worlds()
                        self._reset_graph = cap.graph
                except Exception as exc:  # eager launches are slower, never wrong
                    log.warning("sim: Warp graph capture failed on %s (%s); launching kernels one by one",
                                self.device, exc)
                    self._step_graph = self._reset_graph = None
        zeros = torch.zeros(n, dtype=torch.bool, device=dev)
        self._state = self._read(zeros)
        self._write_rows(torch.arange(n, device=dev))

    # ---- BatchSim ---------------------------------------------------------------------

    @property
    def state(self) -> SimState:
        return self._state

    def reset(self, world_ids: torch.Tensor, qpos: torch.Tensor, qvel: torch.Tensor) -> None:
        ids = world_ids.to(self.device, torch.long)
        if ids.numel() == 0:
            return
        qpos = qpos.detach().to(self.device, torch.float32)
        qvel = qvel.detach().to(self.device, torch.float32)
        if not bool(torch.isfinite(qpos).all() & torch.isfinite(qvel).all()):
            raise ValueError("sim.reset: qpos/qvel contain NaN or Inf")
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
            advice = _overflow_advice(self._or_bits() & self._buffer_bits, self.nconmax, self.njmax)
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

    # ---- internals --------------------------------------------------------------------

    def _physics_step(self) -> None:
        """One policy step on the device: substeps x (mj_step, record the contact sensors, guard)."""
        mjw, d, n = self._mjw, self._d, self.num_worlds
        self._unstable_wp.zero_()
        for s in range(self.substeps):
            mjw.step(self._m, d)
            wp.launch(_record_substep, dim=(n, self.model.nsensordata), inputs=[d.sensordata, s, self._rec_wp])
            wp.launch(
                _guard,
                dim=n,
                inputs=[self.max_speed, self._reset_qpos_wp, self._reset_qvel_wp],
                outputs=[d.qpos, d.qvel, d.qacc_warmstart, self._unstable_wp],
            )

    def _reset_worlds(self) -> None:
        """Worlds in `_mask`: MuJoCo's reset (clears warmstart, forces, time), then the stored reset state."""
        mjw, d = self._mjw, self._d
        mjw.reset_data(self._m, d, reset=self._mask_wp)
        wp.launch(
            _restore,
            dim=self.num_worlds,
            inputs=[self._mask_wp, self._reset_qpos_wp, self._reset_qvel_wp, self._joint_qpos_wp],
            outputs=[d.qpos, d.qvel, d.ctrl],
        )
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
        st, lay = self._state, self.layout
        st.qpos[ids] = self._qpos[ids]
        st.qvel[ids] = self._qvel[ids]
        r, v = lay.root_qpos, lay.root_qvel
        st.root_pos[ids] = st.qpos[ids, r : r + 3]
        st.root_quat[ids] = st.qpos[ids, r + 3 : r + 7]
        st.root_lin_vel[ids] = st.qvel[ids, v : v + 3]
        st.root_ang_vel[ids] = st.qvel[ids, v + 3 : v + 6]
        st.joint_pos[ids] = st.qpos[ids][:, self._joint_qpos]
        st.joint_vel[ids] = st.qvel[ids][:, self._joint_qvel]
        if self.body_state:
            st.body_pos[ids] = self._xpos[ids]
            st.body_vel[ids] = self._cvel[ids]
        for name in ("root_lin_acc", "joint_acc", "joint_torque", "contact_force"):
            getattr(st, name)[ids] = 0.0

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
