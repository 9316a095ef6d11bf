"""The problems a user can fix, one class each, under one `FallkitError` base.

The app catches `FallkitError` once and prints its message as one line with exit
status 2 (no traceback), so every message names what is wrong and what to change.
Everything else is a bug in fallkit or a plugin and keeps its traceback. The
built-in bases (ValueError, RuntimeError) stay so that callers catching those
keep working.
"""

from __future__ import annotations

from pathlib import Path


class FallkitError(Exception):
    """A problem the user can fix; the message is one line naming it and the fix."""


class ConfigError(FallkitError, ValueError):
    """An invalid configuration value; the message names the key."""


class PluginError(FallkitError, RuntimeError):
    """A plugin that cannot be used: import failure, duplicate name or invalid value."""


class RobotSpecError(FallkitError, ValueError):
    """A robot description that cannot be used; the message names robot and field."""


class URDFError(RobotSpecError):
    """A URDF that cannot be turned into a robot; the message names file and element."""


class PoseFileError(FallkitError, ValueError):
    """An end-pose dataset or artist pose file that cannot be used; names the file (and line)."""


class CheckpointError(FallkitError, ValueError):
    """A checkpoint that is missing, unreadable or does not fit this run."""


class RenderError(FallkitError, RuntimeError):
    """Offscreen rendering is unavailable (no OpenGL backend) or failed."""


class DeployError(FallkitError, ValueError):
    """An input of the deploy controller (export folder, state, end pose) that cannot be used."""


class SimBufferError(FallkitError, RuntimeError):
    """mujoco_warp's preallocated contact or constraint buffer overflowed; names the sim.* key to raise."""


def require_file(path: str | Path, what: str, error: type[FallkitError] = FallkitError) -> Path:
    """`path` as a Path when it is an existing file; else `error` saying whether it is missing or a directory."""
    path = Path(path)
    if path.is_dir():
        article = "an" if what[0] in "aeiou" else "a"
        raise error(f"{path}: is a directory, not {article} {what} file")
    if not path.is_file():
        raise error(f"{path}: {what} not found")
    return path


class TrainingError(FallkitError, RuntimeError):
    """Training cannot go on: e.g. its losses became NaN (the run diverged)."""
