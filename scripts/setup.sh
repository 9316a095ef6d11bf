#!/usr/bin/env bash
# Set fallkit up on a fresh machine: a virtual environment in .venv with fallkit,
# its test/export/launcher extras and the plugins under plugins/ installed, and
# OSMesa for headless rendering. Re-running is cheap: it reinstalls only when a
# pyproject.toml (or this script) changed.
set -euo pipefail
cd "$(dirname "$0")/.."
shopt -s nullglob

PYTHON=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  echo "fallkit setup: creating .venv with $($PYTHON --version)"
  "$PYTHON" -m venv .venv
fi

# apt_install PACKAGE WHAT: install a Debian package as root where apt-get exists; otherwise, or if
# that fails, say what is missing and what it costs (never an error: fallkit runs without it).
apt_install() {
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    echo "fallkit setup: installing $1 for $2"
    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "$1" >/dev/null) \
      || echo "fallkit setup: warning: could not install $1; $2 will be unavailable" >&2
  else
    echo "fallkit setup: note: install Debian's $1 for $2" >&2
  fi
}

# Headless rendering (pose contact sheets, fall videos) uses MuJoCo's OSMesa backend.
if ! ldconfig -p 2>/dev/null | grep -q libOSMesa; then
  apt_install libosmesa6 "headless rendering (videos, contact sheets)"
fi
# mode=play's browser test (tests/test_play.py) drives Debian's Chromium, headless, with Playwright;
# without it that test is skipped with its reason.
if ! command -v chromium >/dev/null && ! command -v chromium-browser >/dev/null; then
  apt_install chromium "the browser test of mode=play"
fi

stamp=.venv/.fallkit-setup
want=$(cat scripts/setup.sh pyproject.toml plugins/*/pyproject.toml 2>/dev/null | sha256sum | cut -d' ' -f1)
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ]; then
  exit 0
fi

echo "fallkit setup: installing packages (a few minutes on a fresh machine)"
pip() { .venv/bin/python -m pip "$@" 2>&1 | grep -v "^WARNING: Location" || true; }
pip install -q --upgrade pip
# torch 2.13.0: on this machine pip takes the CPU build from local disk. A GPU user
# installs the CUDA build instead (see README, "GPU").
pip install -q "torch==${FALLKIT_TORCH:-2.13.0}"
pip install -q -e ".[test,export,joblib]"
for plugin in plugins/*/; do
  if [ -f "$plugin/pyproject.toml" ]; then pip install -q --no-deps -e "$plugin"; fi
done
.venv/bin/python -c "import fallkit, mujoco, torchrl, hydra" || { echo "fallkit setup: install failed" >&2; exit 1; }
echo "$want" > "$stamp"
echo "fallkit setup: done"
