"""Simulator backends behind one interface (see `fallkit.sim.base`)."""

from __future__ import annotations

from typing import Any

from fallkit.config.sim import SimConfig
from fallkit.robots.spec import RobotSpec
from fallkit.sim.base import BatchSim, Layout, SimState

__all__ = ["BatchSim", "Layout", "SimState", "make_sim", "sim_options", "BACKENDS"]

BACKENDS = ("mujoco", "warp")


def make_sim(spec: RobotSpec, num_worlds: int, backend: str = "mujoco", **options) -> BatchSim:
    """A BatchSim of `num_worlds` worlds of `spec` on the chosen backend.

    mujoco: MuJoCo C on CPU threads (options: threads).
    warp:   mujoco_warp on a GPU or Warp's CPU device (options: device, nconmax, njmax).
    """
    if backend == "mujoco":
        from fallkit.sim.mujoco_sim import MujocoSim

        return MujocoSim(spec, num_worlds, **options)
    if backend == "warp":
        from fallkit.sim.warp_sim import WarpSim

        return WarpSim(spec, num_worlds, **options)
    raise ValueError(f"sim.backend: unknown backend '{backend}'; choose one of {', '.join(BACKENDS)}")


def sim_options(config: SimConfig) -> dict[str, Any]:
    """make_sim's options from a run's `sim:` section (each backend's own keys only)."""
    options: dict[str, Any] = {"max_speed": config.max_speed}
    if config.backend == "mujoco":
        options["threads"] = config.threads
    else:
        options.update(device=config.device, nconmax=config.nconmax, njmax=config.njmax)
    return options
