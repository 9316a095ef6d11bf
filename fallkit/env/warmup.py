"""`python -m fallkit mode=warmup sim=warp [robot=…]`: fill Warp's kernel cache on purpose.

The warp backend compiles mujoco_warp's kernels for each robot model on a machine's first
run (minutes; `fallkit.sim.warp_setup.preparing_kernels`). Training, evaluation, rendering
and the benchmarks all load them from one cache (`$FALLKIT_WARP_CACHE`, default
`~/.cache/fallkit/warp`), so one warmup per machine, robot and device — e.g. as a cluster's
first job, before a sweep whose jobs should not each pay it — makes every later run start
in seconds. It builds the training environment exactly as training does (same model,
buffers and world count: the same kernels) and steps it once from its initial states.
"""

from __future__ import annotations

from pathlib import Path

from fallkit.config import FallkitConfig
from fallkit.env.build import make_env
from fallkit.errors import ConfigError
from fallkit.robots import robot_spec
from fallkit.sim.warp_setup import warp_cache_dir


def run_warmup(config: FallkitConfig, run_dir: Path) -> dict:
    """Build the training env on warp (compiling what the cache lacks), step it once, say what it took."""
    if config.sim.backend != "warp":
        raise ConfigError("mode=warmup prepares the warp backend's kernels: add sim=warp (mujoco compiles nothing)")
    spec = robot_spec(config.robot)
    env = make_env(config, spec, "train", seed=config.seed)
    env.rand_step(env.reset())
    sim = env.sim
    prepared = sim.prepared
    result = {"robot": spec.name, "device": str(sim.device), "seconds": round(prepared.seconds, 1),
              "modules_compiled": prepared.compiled, "cache": str(warp_cache_dir())}  # fmt: skip
    verb = f"compiled {prepared.compiled} modules" if prepared.compiled else "everything was already in the cache"
    print(f"warmup: {spec.name} on {sim.device}: {verb}, ready in {prepared.seconds:.1f} s; cache {warp_cache_dir()}")
    return result
