"""Start a cluster-shaped v2xlake on one machine, each service its own process, as they would
run on separate machines (see deploy/cluster.md for the per-machine commands):

* a Prefect server (or ``--api-url`` of a running one),
* a Prefect work pool (type process) with a concurrency limit: how many clips run at once,
  and a process worker polling it,
* a Dask scheduler and ``--workers`` Dask worker processes (one thread each) that run the
  stages and their chunks; each worker gets only what a remote machine would get: the
  Prefect API URL, the S3 endpoint and keys, its own working folder,
* optionally (``--s3-dir``) a local S3 server (SeaweedFS ``weed mini``) with bucket ``lake``.

    python deploy/start_cluster.py [--workers 2] [--clips-at-once 2] [--s3-dir DIR]
                                   [--api-url URL] [--home DIR] [--pool v2xlake-cluster]

Prints one JSON line (``{"prefect_api_url", "dask_scheduler", "pool", "env"}``) and the
``export`` lines to run ``v2xlake process ... --runner dask=<scheduler>`` or the deployment
``process-clips-cluster`` against it, then runs until SIGTERM / Ctrl-C and stops everything
it started, each by its process group.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from v2xlake.flows.cluster import (  # noqa: E402
    Service,
    start_dask_scheduler,
    start_dask_worker,
    start_s3,
    wait_for_workers,
)
from v2xlake.flows.runners import thread_env, worker_threads  # noqa: E402
from v2xlake.flows.server import start_server, start_worker, stop_process  # noqa: E402
from v2xlake.flows.settings import v2xlake_home  # noqa: E402


def create_pool(api_url: str, pool: str, limit: int, home: Path) -> None:
    """The work pool (type process) with its concurrency limit: at most ``limit`` flow runs
    (one per clip with the ``process-clips-cluster`` deployment) at a time."""
    env = dict(os.environ, PREFECT_API_URL=api_url, PREFECT_HOME=str(home))
    prefect = [sys.executable, "-m", "prefect"]
    subprocess.run([*prefect, "work-pool", "create", pool, "--type", "process",
                    "--overwrite"], env=env, check=True, capture_output=True)
    subprocess.run([*prefect, "work-pool", "set-concurrency-limit", pool, str(limit)],
                   env=env, check=True, capture_output=True)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--workers", type=int, default=2, help="Dask worker processes")
    p.add_argument("--clips-at-once", type=int, default=2,
                   help="work pool concurrency limit (flow runs, i.e. clips, at once)")
    p.add_argument("--pool", default="v2xlake-cluster")
    p.add_argument("--no-pool", action="store_true",
                   help="no work pool or Prefect worker (runs started by v2xlake process)")
    p.add_argument("--api-url", help="use this Prefect API instead of starting a server")
    p.add_argument("--s3-dir", type=Path, help="start a local S3 server with its data here")
    p.add_argument("--home", type=Path, default=v2xlake_home() / "cluster")
    p.add_argument("--pythonpath", default="",
                   help="extra import paths for the workers (plugins, test doubles)")
    args = p.parse_args()

    def _stop(signum: int, frame: object) -> None:
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, _stop)
    home = args.home.expanduser().resolve()
    home.mkdir(parents=True, exist_ok=True)
    started: list[Service] = []
    procs: list[subprocess.Popen[bytes]] = []
    server = None
    try:
        env: dict[str, str] = {}
        if args.s3_dir is not None:
            s3 = start_s3(args.s3_dir.resolve(), bucket="lake")
            started.append(s3)
            env.update(s3.env())
        if args.api_url:
            api_url = args.api_url
        else:
            server = start_server(home / "prefect")
            api_url = server.api_url
        env["PREFECT_API_URL"] = api_url
        # what every remote process needs, and nothing of this shell's state; a worker's
        # console is its log file, where each task run's lines belong (a quiet CLI in this
        # shell must not silence them)
        worker_env = dict(os.environ, **env, PREFECT_HOME=str(home / "prefect-client"),
                          DO_NOT_TRACK="1", PREFECT_SERVER_ANALYTICS_ENABLED="false",
                          PREFECT_LOGGING_HANDLERS_CONSOLE_LEVEL="INFO",
                          PYTHONPATH=os.pathsep.join(
                              p for p in (str(REPO), args.pythonpath) if p))
        # all workers share this machine's cores: each gets cores // workers threads
        # (numba, BLAS, the stages' pools; flows/runners.py), not every core
        worker_env.update(thread_env(worker_threads(args.workers)))
        sched = start_dask_scheduler(home, env=worker_env)
        started.append(sched)
        for k in range(args.workers):
            wdir = home / f"worker-{k}"
            wdir.mkdir(exist_ok=True)
            started.append(start_dask_worker(sched.address, home, name=f"w{k}",
                                             env=worker_env, cwd=wdir))
        wait_for_workers(sched.address, args.workers)
        if not args.no_pool:
            create_pool(api_url, args.pool, args.clips_at_once, home)
            procs.append(start_worker(api_url, args.pool, home=home, cwd=REPO,
                                      extra_env={k: worker_env[k] for k in
                                                 (*env, "PYTHONPATH")}))
        info = {"prefect_api_url": api_url, "dask_scheduler": sched.address,
                "pool": None if args.no_pool else args.pool, "env": env, "home": str(home)}
        print(json.dumps(info), flush=True)
        for k, v in env.items():
            print(f"export {k}={v}", flush=True)
        print(f"# v2xlake process CLIP... --lake s3://lake/NAME --runner dask={sched.address}",
              flush=True)
        while all(s.proc.poll() is None for s in started) and (
                server is None or server.proc.poll() is None):
            time.sleep(1)
        dead = [s.log_path for s in started if s.proc.poll() is not None]
        print(f"a service stopped: {dead}", file=sys.stderr, flush=True)
        return 1
    except KeyboardInterrupt:
        return 0
    finally:
        for proc in procs:
            stop_process(proc)
        for s in reversed(started):
            s.stop()
        if server is not None:
            server.stop()


if __name__ == "__main__":
    raise SystemExit(main())
