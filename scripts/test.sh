#!/usr/bin/env bash
# The test command of the README: install from the lock, lint, type-check, run the suite
# (benchmarks in tests/bench are not part of it).
set -euo pipefail
# shellcheck disable=SC1091
. "$(dirname "$0")/bootstrap.sh"
ruff check .
mypy
python -m pytest -q "$@"
