#!/usr/bin/env bash
# Set up (if needed), then run the whole test suite: fallkit's tests and every plugin's own tests.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export MUJOCO_GL=${MUJOCO_GL:-osmesa}
shopt -s nullglob
plugin_tests=(plugins/*/tests)
exec .venv/bin/python -m pytest -q -ra tests "${plugin_tests[@]}" "$@"
