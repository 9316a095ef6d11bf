#!/usr/bin/env bash
# Set up (if needed), then the main job: a short training of biped20 on this machine's CPU
# (train=quick: 1024 envs, a 15-minute budget), which ends by evaluating its policy against the
# three standard fall strategies (zero torque, damping, freeze) on falls it never trained on;
# then a video of those falls side by side. Extra arguments are Hydra overrides for the
# training, e.g. `bash scripts/main.sh train.max_minutes=5`.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
export MUJOCO_GL=${MUJOCO_GL:-osmesa}
run_dir="runs/main/$(date +%Y-%m-%d_%H-%M-%S)"
.venv/bin/python -m fallkit robot=biped20 train=quick hydra.run.dir="$run_dir" "$@"
.venv/bin/python -m fallkit mode=render checkpoint="$run_dir" hydra.run.dir="$run_dir/video"
cat <<TXT

Where to look ($run_dir):
  eval.md                  the policy against zero torque, damping and freeze (table)
  *.png                    impact box plots, per-component impact, tracking errors
  learning_curve.png       reward, impact and reward terms over training
  video/                   the falls side by side (policy | zero torque | damping | freeze)
  tensorboard/             .venv/bin/tensorboard --logdir $run_dir/tensorboard
  checkpoints/last.pt      the policy; export it with:
                           .venv/bin/python -m fallkit mode=export checkpoint=$run_dir
TXT
echo
# the answer in one line: the learned policy against the best of the three standard strategies
.venv/bin/python -m fallkit.eval.report "$run_dir"
