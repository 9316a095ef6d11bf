"""What several test modules share: the command line, the tiny training sizes, a composed config (fallkit.app's)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from fallkit.app import composed_config  # noqa: F401  (the tests' composed config: what `python -m fallkit <overrides>` runs with)

# A training small enough for a test: 8 envs × 4 steps, 2 × 16 networks, no evaluation, short falls.
TINY_RUN = ["train=quick", "sim.num_envs=8", "sim.threads=1", "train.num_steps=4", "train.ppo.num_minibatches=2",
            "train.ppo.epochs=2", "train.evaluate=false", "env.episode_length=0.2", "reward.blend_time=0.1"]  # fmt: skip
TINY = [*TINY_RUN, "train.actor_hidden=[16,16]", "train.critic_hidden=[16,16]"]


def fallkit_cli(*args: str, cwd: Path, timeout: float = 300, **popen) -> subprocess.CompletedProcess:
    """`python -m fallkit …` in `cwd`, output captured."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    return subprocess.run([sys.executable, "-m", "fallkit", *args], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=timeout, **popen)  # fmt: skip


def host_reads(fn) -> list[str]:
    """The device-to-host reads (`fallkit.rl.monitor.HOST_READ_OPS`: `.item()`, `bool(tensor)`, `nonzero` …)
    made while `fn` runs, each as "op at file:line" of the innermost Python frame outside torch."""
    from torch.utils._python_dispatch import TorchDispatchMode

    from fallkit.rl.monitor import HOST_READ_OPS

    found: list[str] = []

    class Reads(TorchDispatchMode):
        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            if func._schema.name in HOST_READ_OPS:
                frame = sys._getframe(1)
                while frame is not None and f"{os.sep}torch{os.sep}" in frame.f_code.co_filename:
                    frame = frame.f_back
                found.append(f"{func} at {frame.f_code.co_filename}:{frame.f_lineno}" if frame else f"{func} at ?")
            return func(*args, **(kwargs or {}))

    with Reads():
        fn()
    return found
