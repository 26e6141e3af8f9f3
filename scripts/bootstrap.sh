#!/usr/bin/env bash
# Install v2xlake into ./.venv from the lock file (idempotent; fast when nothing changed).
# Sourced by scripts/demo.sh, scripts/test.sh and .ci/run.
#
# The venv is made to hold exactly requirements.lock (a full closure that `pip check` passes)
# plus v2xlake itself (editable): packages a previous lock had and this one has not are
# removed first. The test oracles of requirements-oracles.lock go to .venv/test-oracles,
# outside the venv's site-packages (see that file). Each step prints one line with what it
# costs on a first install (measured on 2 cores; later runs reuse pip's cache).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"

step() { printf '[bootstrap %s] %s\n' "$1" "$2" >&2; }

if ! python3 -c "import ctypes.util, sys; sys.exit(0 if ctypes.util.find_library('usb-1.0') else 1)"; then
  # open3d needs libusb at import time; it is the only system library the project needs.
  if [ "$(id -u)" = 0 ]; then
    step 0/5 "system library libusb-1.0-0 for open3d (apt, ~0.2 MB, ~20 s)"
    export DEBIAN_FRONTEND=noninteractive
    (apt-get update -qq && apt-get install -y -qq libusb-1.0-0) >/dev/null
  else
    echo "open3d needs libusb-1.0-0: sudo apt-get install libusb-1.0-0" >&2
  fi
fi

PY=${PYTHON:-python3.11}
command -v "$PY" >/dev/null || PY=python3
if [ ! -x .venv/bin/python ]; then
  step 1/5 "creating .venv with $("$PY" --version 2>&1) (~5 s)"
  "$PY" -m venv .venv
fi
# shellcheck disable=SC1091
. .venv/bin/activate
STAMP=.venv/.v2xlake-lock.sha256
WANT="$(sha256sum requirements.lock requirements-oracles.lock pyproject.toml | sha256sum | cut -d' ' -f1)"
if [ ! -f "$STAMP" ] || [ "$(cat "$STAMP")" != "$WANT" ]; then
  step 2/5 "pip itself (~5 s)"
  python -m pip install -q --disable-pip-version-check --upgrade "pip>=24" >/dev/null
  # packages that are installed but not (or no longer) locked; uninstalled before the
  # lock is installed, since two distributions may own the same files (open3d, open3d-cpu)
  STALE="$(python - <<'EOF'
import re
from importlib import metadata

def norm(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()

locked = {norm(line.split("==")[0]) for line in open("requirements.lock")
          if line.strip() and not line.startswith("#")}
keep = locked | {"pip", "setuptools", "wheel", "v2xlake"}
print(" ".join(sorted({norm(d.metadata["Name"]) for d in metadata.distributions()
                       if d.metadata["Name"] and norm(d.metadata["Name"]) not in keep})))
EOF
)"
  if [ -n "$STALE" ]; then
    step 2/5 "removing packages the lock no longer holds: $STALE"
    # shellcheck disable=SC2086
    python -m pip uninstall -q -y $STALE
  fi
  step 3/5 "$(grep -vc '^#' requirements.lock) locked packages: ~2.5 GB in .venv, 2-3 min on a first install from a nearby registry, ~1 min from pip's cache"
  # The lock is the full closure, so --no-deps keeps pip from pulling anything unpinned.
  python -m pip install -q --disable-pip-version-check --no-deps -r requirements.lock
  step 4/5 "test oracles (nuscenes-devkit, scikit-learn) into .venv/test-oracles: ~60 MB, ~20 s"
  # built beside the old folder and swapped in, so a test run in progress keeps its devkit
  rm -rf .venv/test-oracles.new .venv/test-oracles.old
  python -m pip install -q --disable-pip-version-check --no-deps \
    --target .venv/test-oracles.new -r requirements-oracles.lock
  [ ! -d .venv/test-oracles ] || mv .venv/test-oracles .venv/test-oracles.old
  mv .venv/test-oracles.new .venv/test-oracles
  rm -rf .venv/test-oracles.old
  step 5/5 "v2xlake itself, editable (~10 s)"
  # setuptools' build log (its generic notice about editable installs included) goes to a
  # file, shown only when the install fails
  if ! python -m pip install -q --disable-pip-version-check --no-deps -e . \
      > .venv/editable-install.log 2>&1; then
    cat .venv/editable-install.log >&2
    exit 1
  fi
  python -m pip check >&2
  echo "$WANT" > "$STAMP"
  step done "$(du -sh .venv | cut -f1) in .venv"
fi
export PREFECT_SERVER_ANALYTICS_ENABLED=false DO_NOT_TRACK=1 MPLBACKEND=Agg
