"""Start a Prefect server on a free port and a process worker for the ``v2xlake`` pool.

    python deploy/start_server.py [--port N] [--pool v2xlake] [--home ~/.v2xlake/server]

Prints the ``PREFECT_API_URL`` to export, then runs until Ctrl-C and stops both process
groups. Schedules (deploy/prefect.yaml) need this real server: the temporary one that
Prefect starts for a plain ``v2xlake process`` refuses them.
"""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from v2xlake.flows.server import start_server, start_worker, stop_process  # noqa: E402
from v2xlake.flows.settings import v2xlake_home  # noqa: E402


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--port", type=int, default=None)
    p.add_argument("--pool", default="v2xlake")
    p.add_argument("--home", default=str(v2xlake_home() / "server"))
    p.add_argument("--no-worker", action="store_true")
    args = p.parse_args()

    def _stop(signum: int, frame: object) -> None:  # SIGTERM: stop the children too
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, _stop)
    home = Path(args.home).expanduser()
    server = start_server(home, port=args.port)
    print(f"prefect server: {server.api_url} (log {server.log_path})", flush=True)
    print(f"export PREFECT_API_URL={server.api_url}", flush=True)
    env = dict(os.environ, PREFECT_API_URL=server.api_url, PREFECT_HOME=str(home))
    subprocess.run([sys.executable, "-m", "prefect", "work-pool", "create", args.pool,
                    "--type", "process", "--overwrite"], env=env, check=False)
    worker = None
    if not args.no_worker:
        worker = start_worker(server.api_url, args.pool, home=home, cwd=REPO)
        print(f"process worker for pool {args.pool!r} (log {home}/worker-{args.pool}.log)",
              flush=True)
    try:
        while server.proc.poll() is None:
            time.sleep(1)
    except KeyboardInterrupt:
        pass
    finally:
        if worker is not None:
            stop_process(worker)
        server.stop()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
