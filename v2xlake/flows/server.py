"""Start and stop a real ``prefect server`` (and process workers) on a free port.

WHY: schedules only fire on a real server (the temporary one refuses them) and Dask workers
must all talk to one API. Used by ``v2xlake process --runner dask`` when no
``PREFECT_API_URL`` is set, by ``deploy/start_server.py`` and by the tests. Processes are
started in their own process group and stopped by group, so no child outlives them, and
under ``flows/guard.py``, so none outlives its parent either, even a SIGKILLed one; Prefect's
own temporary server gets the same guard (``guard_ephemeral_server``).
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from v2xlake.flows.settings import configure_prefect


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


GUARD = Path(__file__).resolve().with_name("guard.py")


def guarded(cmd: list[str]) -> list[str]:
    """``cmd`` under ``flows/guard.py``: it stops when this process is gone, SIGKILL
    included (a killed CLI or test run left its Prefect server running, #16)."""
    return [sys.executable, str(GUARD), str(os.getpid()), "--", *cmd]


def guard_ephemeral_server() -> None:
    """Make Prefect's temporary server (started for flow runs when no ``PREFECT_API_URL``
    is set) a guarded process too. Prefect starts it in
    ``SubprocessASGIServer._run_uvicorn_command`` and stops it only from ``atexit``; this
    replaces that method by the same command (uvicorn on Prefect's app factory, the same
    environment: Prefect 3.x's code, Apache-2.0) run under the guard. Idempotent;
    importing the server module costs nothing extra, the temporary server needs it."""
    import prefect
    from prefect.server.api import server as prefect_server
    from prefect.settings import get_current_settings

    cls = prefect_server.SubprocessASGIServer
    if getattr(cls, "_v2xlake_guarded", False):
        return

    def run_guarded(self: Any) -> subprocess.Popen[Any]:
        cmd = [sys.executable, "-m", "uvicorn", "--app-dir",
               str(prefect.__module_path__.parent), "--factory",
               "prefect.server.api.server:create_app", "--host", "127.0.0.1",
               "--port", str(self.port), "--log-level", "error", "--lifespan", "on"]
        env = {**os.environ, "PREFECT_UI_ENABLED": "0", "PREFECT__SERVER_EPHEMERAL": "1",
               "PREFECT__SERVER_FINAL": "1",
               **get_current_settings().to_environment_variables(exclude_unset=True)}
        return subprocess.Popen(guarded(cmd), env=env)

    cls._run_uvicorn_command = run_guarded  # type: ignore[method-assign]
    cls._v2xlake_guarded = True  # type: ignore[attr-defined]


def prestart_temporary_server() -> Callable[[], None] | None:
    """Start Prefect's temporary server now, in a background thread, when flows will need
    it (no ``PREFECT_API_URL``, temporary server allowed); returns the wait for it (call it
    before the first flow run), or None when no temporary server will be started.

    WHY: on the first flow run Prefect starts this server (a uvicorn process importing
    Prefect's server: 6-15 s on two cores) and waits for it; started first, it comes up
    while the caller imports the stages (4 s), and on a second core the two overlap. It is
    the same server Prefect would start (``SubprocessASGIServer`` keeps one per process, so
    the flow's client finds it running), under the same guard. Waiting is required:
    Prefect marks the server running before it answers."""
    import threading

    configure_prefect()
    from prefect.settings import PREFECT_API_URL, PREFECT_SERVER_EPHEMERAL_ENABLED

    if PREFECT_API_URL.value() or not PREFECT_SERVER_EPHEMERAL_ENABLED.value():
        return None
    guard_ephemeral_server()
    from prefect.server.api.server import SubprocessASGIServer

    failed: list[BaseException] = []

    def start() -> None:
        try:
            SubprocessASGIServer().start()
        except Exception as e:  # the flow's own start retries it and reports the error
            failed.append(e)

    thread = threading.Thread(target=start, name="v2xlake-prefect-prestart", daemon=True)
    thread.start()
    return thread.join


def _prefect_exe() -> list[str]:
    exe = Path(sys.executable).with_name("prefect")
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "prefect"]


def stop_process(proc: subprocess.Popen[bytes], timeout: float = 15.0) -> None:
    """SIGTERM the process group, then SIGKILL whatever is left."""
    if proc.poll() is not None:
        return
    try:
        os.killpg(proc.pid, signal.SIGTERM)
    except ProcessLookupError:
        return
    try:
        proc.wait(timeout)
    except subprocess.TimeoutExpired:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        proc.wait(5)


@dataclass
class PrefectServer:
    """A running ``prefect server start``: its URL, log file and process."""

    port: int
    home: Path
    log_path: Path
    proc: subprocess.Popen[bytes]
    env: dict[str, str] = field(default_factory=dict)

    @property
    def api_url(self) -> str:
        return f"http://127.0.0.1:{self.port}/api"

    @property
    def ui_url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def healthy(self) -> bool:
        try:
            with urllib.request.urlopen(f"{self.api_url}/health", timeout=2) as r:
                return bool(r.status == 200)
        except OSError:
            return False

    def stop(self) -> None:
        stop_process(self.proc)


def start_server(home: Path, *, port: int | None = None, timeout: float = 120.0,
                 scheduler_loop_seconds: float | None = None, ui: bool = False
                 ) -> PrefectServer:
    """Start a server with its own PREFECT_HOME (SQLite there); wait until /health answers.

    ``ui``: serve the Prefect UI at ``/`` (``deploy/start_server.py`` does by default, so
    the run links the tools print open); off for the servers tests and ``--runner dask``
    start for themselves, where nobody looks at it and it costs start-up time."""
    configure_prefect()
    home = Path(home)
    home.mkdir(parents=True, exist_ok=True)
    port = port or free_port()
    env = dict(os.environ)
    env.pop("PREFECT_API_URL", None)
    env.update({
        "PREFECT_HOME": str(home),
        "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
        "DO_NOT_TRACK": "1",
        "PREFECT_UI_ENABLED": "true" if ui else "false",
        "PREFECT_SERVER_API_HOST": "127.0.0.1",
        "PREFECT_SERVER_API_PORT": str(port),
    })
    if scheduler_loop_seconds is not None:
        env["PREFECT_SERVER_SERVICES_SCHEDULER_LOOP_SECONDS"] = str(scheduler_loop_seconds)
    log_path = home / f"server-{port}.log"
    with open(log_path, "wb") as log:
        proc = subprocess.Popen(
            guarded([*_prefect_exe(), "server", "start", "--host", "127.0.0.1",
                     "--port", str(port)]),
            env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    server = PrefectServer(port, home, log_path, proc, env)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"prefect server exited ({proc.returncode}):\n"
                               f"{log_path.read_text()[-3000:]}")
        if server.healthy():
            return server
        time.sleep(0.5)
    server.stop()
    raise TimeoutError(f"prefect server not healthy after {timeout} s:\n"
                       f"{log_path.read_text()[-3000:]}")


def start_worker(api_url: str, pool: str, *, home: Path, cwd: Path,
                 extra_env: dict[str, str] | None = None,
                 query_seconds: float = 2.0) -> subprocess.Popen[bytes]:
    """``prefect worker start --pool POOL --type process`` against the given API."""
    env = dict(os.environ)
    env.update({"PREFECT_API_URL": api_url, "PREFECT_HOME": str(home),
                "PREFECT_WORKER_QUERY_SECONDS": str(query_seconds),
                "PREFECT_WORKER_PREFETCH_SECONDS": "5",
                "DO_NOT_TRACK": "1", "PREFECT_SERVER_ANALYTICS_ENABLED": "false"})
    env.update(extra_env or {})
    log = open(Path(home) / f"worker-{pool}.log", "ab")  # owned by the child process
    return subprocess.Popen(
        guarded([*_prefect_exe(), "worker", "start", "--pool", pool, "--type", "process"]),
        env=env, cwd=str(cwd), stdout=log, stderr=subprocess.STDOUT, start_new_session=True)


def flush_prefect_logs() -> None:
    """Send buffered run logs now: once the server is gone they would be retried at exit."""
    import sys as _sys

    if "prefect.logging.handlers" not in _sys.modules:
        return
    from prefect.logging.handlers import APILogHandler

    try:
        APILogHandler().flush()
    except Exception:
        pass


@contextmanager
def running_server(home: Path, **kwargs: float) -> Iterator[PrefectServer]:
    """A server for the duration of the block, with PREFECT_API_URL exported meanwhile."""
    server = start_server(home, **kwargs)  # type: ignore[arg-type]
    old = os.environ.get("PREFECT_API_URL")
    os.environ["PREFECT_API_URL"] = server.api_url
    try:
        yield server
    finally:
        flush_prefect_logs()
        if old is None:
            os.environ.pop("PREFECT_API_URL", None)
        else:
            os.environ["PREFECT_API_URL"] = old
        server.stop()
