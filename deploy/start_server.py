"""Start a Prefect server (with its UI) on a free port and a process worker for the
``v2xlake`` pool.

    python deploy/start_server.py [--port N] [--pool v2xlake] [--home ~/.v2xlake/server]
                                  [--no-ui] [--no-worker] [--deploy]

Prints the UI address and the ``PREFECT_API_URL`` to export, creates every work pool that
deploy/prefect.yaml names (type process; existing ones are kept), with ``--deploy`` creates
every deployment of that file (deploy/deploy.py: exit 1 naming any that is missing), then
runs until Ctrl-C / SIGTERM and stops its process groups. Schedules need this real server:
the temporary one that Prefect starts for a plain ``v2xlake process`` refuses them. The UI
is served at ``/`` (run pages at ``/runs/flow-run/<id>``); ``--no-ui`` leaves only the API.
"""

from __future__ import annotations

import argparse
import signal
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from v2xlake.flows.deployments import (  # noqa: E402
    DeployError,
    declared_pools,
    deploy_all,
    ensure_pools,
)
from v2xlake.flows.server import start_server, start_worker, stop_process  # noqa: E402
from v2xlake.flows.settings import v2xlake_home  # noqa: E402


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--port", type=int, default=None)
    p.add_argument("--pool", default="v2xlake")
    p.add_argument("--home", default=str(v2xlake_home() / "server"))
    p.add_argument("--no-worker", action="store_true")
    p.add_argument("--no-ui", action="store_true", help="serve the API only, no Prefect UI")
    p.add_argument("--deploy", action="store_true",
                   help="create every deployment of deploy/prefect.yaml (fails naming any "
                        "that is missing)")
    args = p.parse_args()

    def _stop(signum: int, frame: object) -> None:  # SIGTERM: stop the children too
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, _stop)
    home = Path(args.home).expanduser()
    server = start_server(home, port=args.port, ui=not args.no_ui)
    print(f"prefect server: {server.api_url} (log {server.log_path})", flush=True)
    if not args.no_ui:
        print(f"prefect UI: {server.ui_url}/", flush=True)
    print(f"export PREFECT_API_URL={server.api_url}", flush=True)
    worker = None
    try:
        pools = [args.pool, *(p for p in declared_pools() if p != args.pool)]
        for pool in ensure_pools(server.api_url, pools):
            print(f"work pool created: {pool}", flush=True)
        if args.deploy:
            res = deploy_all(server.api_url)
            print(f"deployments: {', '.join(res.deployments)}", flush=True)
    except DeployError as e:
        print(f"error: {e}", file=sys.stderr, flush=True)
        server.stop()
        return 1
    except BaseException:
        server.stop()
        raise
    if not args.no_worker:
        worker = start_worker(server.api_url, args.pool, home=home, cwd=REPO)
        print(f"process worker for pool {args.pool!r} (log {home}/worker-{args.pool}.log)",
              flush=True)
    print("ready (Ctrl-C or SIGTERM stops the server and the worker)", flush=True)
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
