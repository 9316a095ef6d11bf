"""fallkit: learn soft, stylized falls for legged robots (Robot Crash Course)."""

__version__ = "0.1.0"

import os as _os

# Offscreen rendering (mode=render) needs its OpenGL backend chosen before mujoco is
# imported. Without a display, OSMesa (software) is the one that works everywhere;
# MUJOCO_GL=egl picks a GPU. Harmless when OSMesa is missing until something renders.
if "MUJOCO_GL" not in _os.environ and not _os.environ.get("DISPLAY"):
    _os.environ["MUJOCO_GL"] = "osmesa"
