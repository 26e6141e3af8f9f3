"""Prefect's temporary server, started once and shared by later calls (the default when
``PREFECT_API_URL`` is unset).

WHY (#26, fixed cost of a real call): Prefect's own temporary server belongs to the process
that started it, so every ``v2xlake process`` call paid its start again (uvicorn importing
Prefect's server and migrating its SQLite database: 6-15 s on two cores, more than every other
fixed cost together). This module starts the same server (the same uvicorn command on
Prefect's app factory in its ephemeral mode, the same ``PREFECT_HOME`` database) under
``flows/keeper.py``, detached from the caller, and records it in ``PREFECT_HOME``; a later
call finds it there, checks that it answers, and points ``PREFECT_API_URL`` at it: no setup
by the user, and no server left behind (the keeper stops it ``V2XLAKE_SERVER_IDLE_S``
seconds, default 600, after its last user exited; a user holds a shared ``flock`` on the
lease file for its lifetime, which the kernel drops even on SIGKILL).

``V2XLAKE_SHARED_SERVER=0`` goes back to Prefect's per-process temporary server. Only the
standard library is imported here: the lookup runs before Prefect is imported, so that
Prefect reads the URL from the environment like a user's own ``PREFECT_API_URL``.
"""

from __future__ import annotations

import atexit
import contextlib
import fcntl
import importlib.metadata
import importlib.util
import json
import os
import socket
import subprocess
import sys
import threading
import time
import urllib.request
from collections.abc import Callable
from pathlib import Path

from v2xlake.flows import keeper
from v2xlake.flows.guard import alive

KEEPER = Path(keeper.__file__).resolve()
IDLE_S = 600.0
START_TIMEOUT_S = 180.0
_lease_fd: int | None = None  # held (shared flock) until this process exits
_started: subprocess.Popen[bytes] | None = None  # the keeper this process started, if any


def enabled() -> bool:
    """Shared unless switched off, or a user's ``PREFECT_API_URL`` / Prefect setting that
    forbids a temporary server is in the environment."""
    if os.environ.get("PREFECT_API_URL"):
        return False
    if os.environ.get("V2XLAKE_SHARED_SERVER", "1").lower() in ("0", "false", "no", "off"):
        return False
    return os.environ.get("PREFECT_SERVER_ALLOW_EPHEMERAL_MODE", "true").lower() not in (
        "0", "false", "no", "off")


def idle_seconds() -> float:
    return float(os.environ.get("V2XLAKE_SERVER_IDLE_S", IDLE_S))


def _home() -> Path:
    from v2xlake.flows.settings import configure_prefect

    configure_prefect()  # PREFECT_HOME (user values win)
    home = Path(os.environ["PREFECT_HOME"]).expanduser()
    home.mkdir(parents=True, exist_ok=True)
    return home


def identity() -> dict[str, str]:
    """What a reused server must match: the interpreter, Prefect's version and the database
    (another venv or Prefect release gets a server of its own)."""
    return {"python": sys.executable, "prefect": importlib.metadata.version("prefect"),
            "database": os.environ.get("PREFECT_API_DATABASE_CONNECTION_URL", "")}


def healthy(url: str, timeout: float = 1.0) -> bool:
    try:
        with urllib.request.urlopen(f"{url}/health", timeout=timeout) as r:
            return bool(r.status == 200)
    except OSError:
        return False


def _hold_lease(home: Path) -> None:
    """A shared lock on the lease for this process's lifetime (the keeper stops the server
    only when nobody holds it); touched now and at exit, so idle counts from the last use."""
    global _lease_fd
    if _lease_fd is not None:
        return
    fd = _lease_fd = keeper.hold_lease(home / keeper.LEASE)

    def touch() -> None:
        with contextlib.suppress(OSError):
            os.utime(fd)

    atexit.register(touch)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _start(home: Path, ident: dict[str, str]) -> tuple[str, subprocess.Popen[bytes]]:
    """The server under its keeper, detached (its own session), recorded in the state file."""
    spec = importlib.util.find_spec("prefect")
    assert spec is not None and spec.origin is not None
    port = _free_port()
    cmd = [sys.executable, "-m", "uvicorn", "--app-dir", str(Path(spec.origin).parent.parent),
           "--factory", "prefect.server.api.server:create_app", "--host", "127.0.0.1",
           "--port", str(port), "--log-level", "error", "--lifespan", "on"]
    env = {**os.environ, "PREFECT_UI_ENABLED": "0", "PREFECT__SERVER_EPHEMERAL": "1",
           "PREFECT__SERVER_FINAL": "1"}
    env.pop("PREFECT_API_URL", None)
    with open(home / "shared-server.log", "ab") as log:
        proc = subprocess.Popen(
            [sys.executable, str(KEEPER), str(home), str(idle_seconds()), "--", *cmd],
            env=env, stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT,
            start_new_session=True, close_fds=True)
    global _started
    _started = proc
    url = f"http://127.0.0.1:{port}/api"
    keeper.write_state(home / keeper.STATE,
                       {"pid": proc.pid, "url": url, "started": time.time(), **ident})
    return url, proc


def _wait(url: str, proc: subprocess.Popen[bytes], home: Path) -> None:
    deadline = time.monotonic() + START_TIMEOUT_S
    while time.monotonic() < deadline:
        if healthy(url):
            return
        if proc.poll() is not None:
            raise RuntimeError(f"the shared Prefect server exited ({proc.returncode}); log: "
                               f"{home / 'shared-server.log'}")
        time.sleep(0.1)
    raise TimeoutError(f"the shared Prefect server did not answer in {START_TIMEOUT_S:.0f} s; "
                       f"log: {home / 'shared-server.log'}")


def attach() -> Callable[[], None] | None:
    """Point this process at the shared server, starting it if none answers; returns the
    wait for it to answer (call it before the first flow run; it may start meanwhile), or
    None when Prefect is not to use a shared server (see ``enabled``).

    Sets ``PREFECT_API_URL`` in ``os.environ``: call before Prefect is imported (Prefect
    reads its settings then), and so that Dask workers started later inherit it. Starts of
    concurrent callers are serialised by an exclusive lock held until the server answers."""
    if not enabled():
        return None
    home = _home()
    _hold_lease(home)
    ident = identity()
    lock = os.open(home / "shared-server.start.lock", os.O_RDWR | os.O_CREAT, 0o600)
    fcntl.flock(lock, fcntl.LOCK_EX)
    try:
        state = json.loads((home / keeper.STATE).read_text())
    except (OSError, ValueError):
        state = {}
    if (state.get("url") and all(state.get(k) == v for k, v in ident.items())
            # a generous timeout: a busy server answers late, and replacing it would leave
            # two running until the first one's users are done
            and alive(int(state.get("pid", 0))) and healthy(str(state["url"]), timeout=10.0)):
        os.close(lock)
        os.environ["PREFECT_API_URL"] = str(state["url"])
        return lambda: None
    try:
        url, proc = _start(home, ident)
    except BaseException:
        os.close(lock)
        raise
    os.environ["PREFECT_API_URL"] = url
    failed: list[BaseException] = []

    def wait_then_unlock() -> None:
        try:
            _wait(url, proc, home)
        except BaseException as e:
            failed.append(e)
        finally:
            os.close(lock)  # the next caller finds it answering (or starts its own)

    thread = threading.Thread(target=wait_then_unlock, name="v2xlake-shared-server",
                              daemon=True)
    thread.start()

    def wait() -> None:
        thread.join()
        if failed:
            raise failed[0]

    return wait


def stop(home: Path | None = None) -> bool:
    """Stop the shared server now (tests, or a user who wants it gone): SIGTERM its keeper,
    which stops the server and removes the state file. True when one was running."""
    home = home or _home()
    pid = keeper.state_pid(home / keeper.STATE)
    if pid is None or not alive(pid):
        return False
    os.kill(pid, 15)
    if _started is not None and _started.pid == pid:  # our child: reap it (no zombie)
        _started.wait(15)
        return True
    deadline = time.monotonic() + 15
    while alive(pid) and time.monotonic() < deadline:
        time.sleep(0.1)
    return True
