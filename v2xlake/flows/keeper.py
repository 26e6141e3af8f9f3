"""Keep a shared Prefect API server alive while it is used, stop it when idle (stdlib only).

    python keeper.py HOME IDLE_S [NAME] -- COMMAND [ARGS...]

WHY: Prefect's temporary server lives as long as the process that started it, so every
``v2xlake process`` call without ``PREFECT_API_URL`` paid its start (a uvicorn process
importing Prefect's server: 6-15 s on two cores, the largest part of a real call's fixed
cost, #26). ``flows/shared_server.py`` starts the same server once, under this keeper,
detached from the caller, and later calls find it through the state file in ``HOME``.

``NAME`` (default ``shared-server``) names its files in ``HOME``: the state file
``NAME.json`` and the lease ``NAME.lease``; the warm process (``flows/warm.py``) runs under a
keeper of its own with another name.

The keeper makes a process group of its own, starts the command in it (SIGTERMed if the
keeper dies, even by SIGKILL: ``PR_SET_PDEATHSIG``, as in ``guard.py``) and every ``POLL_S``
stops the group and exits when

- the command has exited,
- ``HOME`` is gone (a test's temporary home was removed), or
- no process holds the lease file (each user holds a shared ``flock`` on it for its
  lifetime; the kernel drops it when the user exits, SIGKILL included) and either the lease
  was last touched (by a user attaching or exiting) more than ``IDLE_S`` seconds ago or the
  state file names another server (a caller found this one not answering and replaced it).

The idle decision is taken holding the lease exclusively, and the state file is removed
before the lock is let go, so a user that attaches meanwhile waits and then starts a fresh
server instead of finding one about to stop.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import FrameType
from typing import Any

from v2xlake.flows.guard import die_with_parent, stop_group

POLL_S = 1.0
NAME = "shared-server"
STATE = f"{NAME}.json"
LEASE = f"{NAME}.lease"


# ---- the protocol's user side (flows/shared_server.py, flows/warm.py): one spelling of it
def write_state(path: Path, state: dict[str, Any]) -> None:
    """Write a state file whole (a temporary file renamed over it): a reader never sees half
    of one."""
    tmp = path.with_name(f"{path.name}.{os.getpid()}")
    tmp.write_text(json.dumps(state))
    os.replace(tmp, path)


def state_pid(path: Path) -> int | None:
    """The keeper's pid a state file names; None when it is missing or unreadable."""
    try:
        return int(json.loads(path.read_text())["pid"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def hold_lease(lease: Path) -> int:
    """A shared lock on ``lease`` for as long as the returned descriptor stays open (the
    kernel drops it when the holder exits, SIGKILL included), touched now: the keeper stops
    its command only when nobody holds the lease, and counts idleness from the last touch."""
    fd = os.open(lease, os.O_RDWR | os.O_CREAT, 0o600)
    fcntl.flock(fd, fcntl.LOCK_SH)  # waits while a keeper decides to stop (milliseconds)
    with contextlib.suppress(OSError):
        os.utime(fd)
    return fd


def _owns_state(state: Path) -> bool:
    """Whether the state file still names this keeper (a replacement server rewrites it)."""
    return state_pid(state) == os.getpid()


def _drop_state(state: Path) -> None:
    if _owns_state(state):
        with contextlib.suppress(OSError):
            state.unlink()


def keep(home: Path, idle_s: float, cmd: list[str], name: str = NAME) -> int:
    if os.getsid(0) != os.getpid():
        os.setsid()
    state = home / f"{name}.json"
    lease = home / f"{name}.lease"
    lease.touch()
    proc = subprocess.Popen(cmd, preexec_fn=die_with_parent)

    def on_signal(sig: int, _frame: FrameType | None) -> None:
        _drop_state(state)
        stop_group(proc)
        sys.exit(128 + sig)

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    started = time.monotonic()
    while True:
        try:
            code = proc.wait(POLL_S)
            _drop_state(state)
            return code
        except subprocess.TimeoutExpired:
            pass
        if not home.is_dir():  # a removed home (a test's temporary one)
            stop_group(proc)
            return 0
        try:
            fd = os.open(lease, os.O_RDWR | os.O_CREAT)
        except OSError:
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:  # a user holds it: in use
            os.close(fd)
            continue
        try:
            # replaced (the state file names another server; it appears just after our
            # start) or idle: stop, but only while no user holds the lease
            replaced = time.monotonic() - started > 30 and not _owns_state(state)
            if replaced or time.time() - os.fstat(fd).st_mtime > idle_s:
                _drop_state(state)  # before the lock goes: a new user starts a fresh server
                stop_group(proc)
                return 0
        finally:
            os.close(fd)  # releases the lock


def main(argv: list[str]) -> int:
    if len(argv) >= 5 and argv[3] == "--":
        return keep(Path(argv[0]), float(argv[1]), argv[4:], name=argv[2])
    if len(argv) < 4 or argv[2] != "--":
        print(__doc__, file=sys.stderr)
        return 2
    return keep(Path(argv[0]), float(argv[1]), argv[3:])


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
