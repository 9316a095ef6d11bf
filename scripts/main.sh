#!/usr/bin/env bash
# Set up (if needed), then the main job: falls of biped20 under the three standard
# strategies (zero torque, damping, freeze), with impact figures. Extra arguments
# are Hydra overrides, e.g. `bash scripts/main.sh eval.trials=512`.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export MUJOCO_GL=${MUJOCO_GL:-osmesa}
exec .venv/bin/python -m fallkit mode=eval robot=biped20 "$@"
