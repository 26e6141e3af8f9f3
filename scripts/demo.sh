#!/usr/bin/env bash
# The main job of the README: install from the lock, then simulate a two-vehicle clip and run
# every stage on it through Prefect (`v2xlake demo --help` for options).
set -euo pipefail
# shellcheck disable=SC1091
. "$(dirname "$0")/bootstrap.sh"
exec v2xlake demo "$@"
