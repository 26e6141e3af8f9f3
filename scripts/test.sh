#!/usr/bin/env bash
# The test command of the README: lint, types, then the whole suite (benchmarks excluded).
set -euo pipefail
cd "$(dirname "$0")/.."
export PREFECT_SERVER_ANALYTICS_ENABLED=false DO_NOT_TRACK=1 MPLBACKEND=Agg
ruff check .
mypy
python -m pytest -q "$@"
