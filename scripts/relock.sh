#!/usr/bin/env bash
# Regenerate requirements.lock after a change to pyproject.toml's dependencies: resolve
# v2xlake[dev,bench] in a scratch venv, keeping every version the current lock pins unless the
# new ranges exclude it (the lock is a constraint, not a requirement), check the result with
# `pip check` and write the frozen closure back. Takes 3-6 minutes on 2 cores.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
PY=${PYTHON:-python3.11}
command -v "$PY" >/dev/null || PY=python3
TMP="$(mktemp -d)"
trap 'rm -rf "$TMP"' EXIT
echo "[relock] scratch venv in $TMP with $("$PY" --version 2>&1)" >&2
"$PY" -m venv "$TMP/venv"
"$TMP/venv/bin/python" -m pip install -q --disable-pip-version-check --upgrade "pip>=24"
grep -v '^#' requirements.lock > "$TMP/constraints.txt"
echo "[relock] resolving v2xlake[dev,bench] (the old lock as constraints)" >&2
"$TMP/venv/bin/python" -m pip install -q --disable-pip-version-check \
  -c "$TMP/constraints.txt" ".[dev,bench]"
"$TMP/venv/bin/python" -m pip check
{
  grep '^#' requirements.lock
  # --all keeps setuptools (the wheel test builds without build isolation); pip is not locked
  "$TMP/venv/bin/python" -m pip freeze --all --exclude-editable \
    | grep -viE '^(pip|v2xlake)( |==)'
} > "$TMP/lock"
mv "$TMP/lock" requirements.lock
echo "[relock] requirements.lock: $(grep -vc '^#' requirements.lock) packages" >&2
