#!/usr/bin/env bash
# Set up (if needed), then run the whole test suite: fallkit's tests and every plugin's own tests.
# --durations: the slowest tests in every CI log, so a suite drifting toward its 15-minute budget shows why.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export MUJOCO_GL=${MUJOCO_GL:-osmesa}
shopt -s nullglob
plugin_tests=(plugins/*/tests)
exec .venv/bin/python -m pytest -q -ra --durations=15 tests "${plugin_tests[@]}" "$@"
