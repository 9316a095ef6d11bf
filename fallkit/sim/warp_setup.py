"""Warp and mujoco_warp plumbing for the warp backend (`fallkit.sim.warp_sim`).

Warp's initialisation with fallkit's kernel cache, the choice of device, the
sizes of mujoco_warp's contact and constraint buffers (and what to raise when
they overflow), the device model, and graph capture. The raw-physics benchmark
(benchmarks/sim_throughput.py) builds its model with the same functions, so both
run the same kernels.
"""

from __future__ import annotations

import gc
import logging
import math
import os
import re
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import mujoco
import torch
import warp as wp

from fallkit.errors import ConfigError

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


def _cached_modules(cache: Path) -> set[str]:
    """Names of the compiled modules in Warp's kernel cache (one folder per module variant)."""
    return {p.name for p in cache.glob("*/wp_*") if p.is_dir()} if cache.is_dir() else set()


@dataclass
class Prepared:
    """What `preparing_kernels` did: its time and the modules it compiled (the rest were loaded)."""

    seconds: float = 0.0
    compiled: int = 0


@contextmanager
def preparing_kernels(what: str, device: str, notice_after: float = 3.0, every: float = 20.0) -> Iterator[Prepared]:
    """Say what Warp is doing while it prepares `what`'s kernels on `device`.

    Loading cached kernels takes seconds and says nothing loud. Compiling them (the first run on a
    machine, or after a Warp or model change) takes minutes, and Warp itself prints nothing at the
    log level fallkit uses: so once compiled modules have started to appear in the cache and the
    preparation has run `notice_after` seconds, one line says what is compiled, roughly how long it
    takes and where the cache goes, then a progress line every `every` seconds (modules compiled so
    far), and one line when it is done.
    """
    init_warp()
    cache = warp_cache_dir()
    before = _cached_modules(cache)
    start = time.perf_counter()
    done = threading.Event()
    noticed = threading.Event()

    def compiled() -> int:
        return len(_cached_modules(cache) - before)

    def watch() -> None:
        # a warm start only loads: it never adds a module, so it never hears of compiling
        while not done.wait(min(0.5, notice_after)):
            if compiled() and time.perf_counter() - start >= notice_after:
                break
        else:
            return
        noticed.set()
        log.warning(
            "warp: compiling %s's kernels for %s (once per machine and Warp version: about 1-3 min on a "
            "CPU, several minutes on a GPU) into %s; later runs load them in seconds "
            "(python -m fallkit mode=warmup sim=warp fills the cache ahead)", what, device, cache,
        )  # fmt: skip
        while not done.wait(every):
            log.warning("warp: still compiling: %d modules so far, %.0f s", compiled(), time.perf_counter() - start)

    watcher = threading.Thread(target=watch, name="warp-compile-notice", daemon=True)
    watcher.start()
    prepared = Prepared()
    try:
        yield prepared
    finally:
        done.set()
        watcher.join()
        prepared.seconds = time.perf_counter() - start
        prepared.compiled = compiled()
        (log.warning if noticed.is_set() else log.info)(
            "warp: %s's kernels ready on %s in %.1f s (%d modules compiled, the rest loaded from %s)",
            what, device, prepared.seconds, prepared.compiled, cache,
        )  # fmt: skip


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


# ---- buffer sizes and overflows ------------------------------------------------------------

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


def buffer_overflow_bits() -> int:
    """mujoco_warp's overflow bits that mean dropped contacts or constraint rows (not the
    solver's iteration limits, nor EPA's polytope size, which only cost accuracy, as in MuJoCo C)."""
    from mujoco_warp import OverflowType as O

    return int(O.NEFC | O.NJMAX_NNZ | O.BROADPHASE | O.NARROWPHASE | O.CCD | O.CONTACT_MATCH | O.NVMAX)


def overflow_advice(bits: int, nconmax: int, njmax: int) -> str:
    """Which setting to raise for mujoco_warp's overflow `bits` (dropped contacts/constraints)."""
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


# ---- the device model and graphs ------------------------------------------------------------


def put_warp_model(model: mujoco.MjModel, num_worlds: int, per_world_gains: bool):
    """The device model, as both fallkit and the raw benchmark build it (same kernels)."""
    import mujoco_warp as mjw

    # per world: the PD gains (strategies, gain randomisation) and the friction (randomisation)
    batch = {"actuator_gainprm": num_worlds, "actuator_biasprm": num_worlds, "geom_friction": num_worlds} if per_world_gains else None
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
def no_gc() -> Iterator[None]:
    """Python's garbage collector paused: a stale Warp graph finalised during capture
    would record its destructor into the new graph."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()


def capture(device, launch: Callable[[], None]):
    """The Warp graph of the kernels `launch` runs on `device` (call inside `no_gc`)."""
    with wp.ScopedCapture(device=device) as cap:
        launch()
    return cap.graph
