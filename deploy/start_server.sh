#!/usr/bin/env bash
# Prefect server on a free port + a process worker for pool "v2xlake" (see start_server.py).
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
exec python "$here/start_server.py" "$@"
