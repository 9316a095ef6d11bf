"""`python -m fallkit …` run from a benchmark, as a user runs it.

A benchmark that measures through the command line must fail the way the command line does: the
child's own one-line error (a bad override, a missing checkpoint), then one line naming the
command, and the benchmark's exit, not a CalledProcessError traceback on top (or, with the
output captured, instead) of the reason.
"""

from __future__ import annotations

import os
import subprocess
import sys


def fallkit(*overrides: str, quiet: bool = False) -> str:
    """Run `python -m fallkit OVERRIDES`; its output goes to the terminal, or with `quiet` is kept and returned
    (shown only when it fails). A failure ends the calling benchmark with the command and its exit status."""
    cmd = [sys.executable, "-m", "fallkit", *overrides]
    done = subprocess.run(cmd, capture_output=quiet, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    if done.returncode != 0:
        if quiet:
            sys.stderr.write(done.stderr[-3000:])
        script = os.path.basename(sys.argv[0])
        sys.exit(f"{script}: `python -m fallkit {' '.join(overrides)}` failed (exit {done.returncode})")
    return done.stdout if quiet else ""
