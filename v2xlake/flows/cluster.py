"""The services of a cluster-shaped run, each its own process: an S3 server, a Dask scheduler,
Dask workers (the Prefect server is ``flows.server``).

WHY separate processes: on a real cluster the scheduler, each worker, the Prefect API and the
object store run on different machines and know each other only by address. Starting them
here the same way (``dask scheduler`` / ``dask worker ADDRESS`` command lines, ``weed mini``
for S3) means a run on one machine exercises exactly what a run across machines does: the
workers import the code themselves, reach the lake only through its URI and report to the
Prefect API named by ``PREFECT_API_URL``. Used by ``deploy/start_cluster.py``,
``tests/test_cluster.py`` and ``tests/bench/bench_scale.py``. Every process runs under
``flows/guard.py`` (it dies with the process that started it, SIGKILL included) in its own
process group, and is stopped by group (``flows.server.stop_process``).
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from v2xlake.flows.server import free_port, guarded, stop_process

WEED_PORTS = ("master.port", "master.port.grpc", "volume.port", "volume.port.grpc",
              "filer.port", "filer.port.grpc", "s3.port", "s3.port.grpc", "admin.port",
              "admin.port.grpc", "webdav.port", "s3.port.iceberg", "s3.port.lance")


@dataclass
class Service:
    """A started process and its log; ``stop()`` ends its process group."""

    proc: subprocess.Popen[bytes]
    log_path: Path

    def stop(self) -> None:
        stop_process(self.proc)

    def tail(self, n: int = 3000) -> str:
        try:
            return self.log_path.read_text(errors="replace")[-n:]
        except OSError:
            return ""


@dataclass
class S3Server(Service):
    endpoint: str
    bucket: str
    access_key: str
    secret_key: str

    def env(self) -> dict[str, str]:
        """What a client (pyarrow, DuckDB httpfs, boto3, a Dask worker) needs to reach it."""
        return {"AWS_ENDPOINT_URL": self.endpoint, "AWS_ACCESS_KEY_ID": self.access_key,
                "AWS_SECRET_ACCESS_KEY": self.secret_key, "AWS_REGION": "us-east-1",
                "AWS_EC2_METADATA_DISABLED": "true"}


def _spawn(cmd: list[str], log_path: Path, env: dict[str, str],
           cwd: Path | None = None) -> subprocess.Popen[bytes]:
    log_path.parent.mkdir(parents=True, exist_ok=True)
    with open(log_path, "wb") as log:  # the child keeps its own descriptor
        return subprocess.Popen(guarded(cmd), env=env, cwd=None if cwd is None else str(cwd),
                                stdout=log, stderr=subprocess.STDOUT, start_new_session=True)


def _exe(name: str) -> str:
    """A console script of this environment (``weed``, ``dask``), else from PATH."""
    here = Path(sys.executable).with_name(name)
    found = str(here) if here.exists() else shutil.which(name)
    if not found:
        raise FileNotFoundError(f"{name} not found next to {sys.executable} or on PATH")
    return found


def start_s3(data_dir: Path, *, bucket: str = "lake", access_key: str = "v2xlake",
             secret_key: str = "v2xlake-secret", timeout: float = 60.0) -> S3Server:
    """SeaweedFS ``weed mini`` (master, volume, filer, S3 gateway in one process) on free
    127.0.0.1 ports with one bucket; returns once a PUT succeeds."""
    data_dir = Path(data_dir)
    data_dir.mkdir(parents=True, exist_ok=True)
    ports = {name: free_port() for name in WEED_PORTS}
    env = dict(os.environ, AWS_ACCESS_KEY_ID=access_key, AWS_SECRET_ACCESS_KEY=secret_key)
    log = data_dir / "weed.log"
    proc = _spawn([_exe("weed"), "mini", f"-dir={data_dir}", "-ip=127.0.0.1",
                   "-ip.bind=127.0.0.1", "-master.telemetry=false", "-admin.ui=false",
                   f"-bucket={bucket}", *[f"-{k}={v}" for k, v in ports.items()]], log, env)
    server = S3Server(proc, log, f"http://127.0.0.1:{ports['s3.port']}", bucket, access_key,
                      secret_key)
    import boto3

    client = boto3.client("s3", endpoint_url=server.endpoint, region_name="us-east-1",
                          aws_access_key_id=access_key, aws_secret_access_key=secret_key)
    deadline = time.monotonic() + timeout
    while True:
        try:
            client.put_object(Bucket=bucket, Key="probe/ready", Body=b"1")
            client.delete_object(Bucket=bucket, Key="probe/ready")
            return server
        except Exception:
            if proc.poll() is not None or time.monotonic() > deadline:
                server.stop()
                raise RuntimeError(f"weed mini did not come up:\n{server.tail()}") from None
            time.sleep(0.3)


@dataclass
class DaskScheduler(Service):
    address: str


def start_dask_scheduler(log_dir: Path, *, port: int | None = None,
                         env: dict[str, str] | None = None,
                         timeout: float = 60.0) -> DaskScheduler:
    """``dask scheduler`` on 127.0.0.1 (no dashboard); returns once it listens."""
    port = port or free_port()
    log = Path(log_dir) / f"dask-scheduler-{port}.log"
    proc = _spawn([_exe("dask"), "scheduler", "--host", "127.0.0.1", "--port", str(port),
                   "--no-dashboard", "--no-show"], log, dict(env or os.environ))
    address = f"tcp://127.0.0.1:{port}"
    sched = DaskScheduler(proc, log, address)
    deadline = time.monotonic() + timeout
    while "Scheduler at:" not in sched.tail(100_000):
        if proc.poll() is not None or time.monotonic() > deadline:
            sched.stop()
            raise RuntimeError(f"dask scheduler did not start:\n{sched.tail()}")
        time.sleep(0.2)
    return sched


def start_dask_worker(address: str, log_dir: Path, *, name: str, nthreads: int = 1,
                      env: dict[str, str] | None = None, cwd: Path | None = None,
                      memory_limit: str = "0") -> Service:
    """``dask worker ADDRESS`` as its own process (its own interpreter, environment and
    working directory, as on another machine); single-threaded by default: the stages hold
    the GIL or run their own thread pools."""
    safe = re.sub(r"[^A-Za-z0-9_.-]", "_", name)
    log = Path(log_dir) / f"dask-worker-{safe}.log"
    proc = _spawn([_exe("dask"), "worker", address, "--name", name, "--nthreads",
                   str(nthreads), "--nworkers", "1", "--memory-limit", memory_limit,
                   "--no-dashboard", "--local-directory", str(Path(log_dir) / f"dw-{safe}")],
                  log, dict(env or os.environ), cwd)
    return Service(proc, log)


def wait_for_workers(address: str, n: int, timeout: float = 90.0) -> None:
    """Block until the scheduler at ``address`` has ``n`` workers."""
    from distributed import Client

    with Client(address, timeout=timeout) as client:
        client.wait_for_workers(n, timeout=timeout)
