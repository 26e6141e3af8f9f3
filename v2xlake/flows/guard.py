"""Run a command that must not outlive the process that started it (stdlib only).

    python guard.py PARENT_PID -- COMMAND [ARGS...]

WHY: a Prefect server (the temporary one Prefect starts for a flow run without
``PREFECT_API_URL``, or ``flows.server.start_server``'s) is a child process. When its parent
ends normally it is stopped (``atexit`` / ``stop_process``), but a parent killed with SIGKILL
runs no code, and the server was left running, holding a port and its SQLite database (9 of
14 kills in #16). Linux's ``PR_SET_PDEATHSIG`` fires when the *thread* that forked the child
exits, which in a thread pool is not the parent's death, so this supervisor polls instead:
it makes a process group of its own, starts the command in it (with ``PR_SET_PDEATHSIG``
set in the command, which is reliable here because the guard forks from its only thread,
so even a SIGKILLed guard takes the command with it), forwards SIGTERM/SIGINT to the group,
exits with the command's status, and stops the group (SIGTERM, then SIGKILL) as soon as its
own parent is gone.

It is a file run by path (no package import: starts in ~20 ms) and imports nothing but the
standard library.
"""

from __future__ import annotations

import ctypes
import os
import signal
import subprocess
import sys
from types import FrameType

POLL_S = 0.25
GRACE_S = 5.0
PR_SET_PDEATHSIG = 1
try:
    _LIBC: ctypes.CDLL | None = ctypes.CDLL(None) if sys.platform == "linux" else None
except OSError:  # the polling below still applies
    _LIBC = None


def alive(pid: int) -> bool:
    """Whether process ``pid`` exists (one of another user counts: it is not ours to reuse,
    but it is there)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def die_with_parent() -> None:
    """In the child, before exec: SIGTERM it when its parent (the guard, the shared server's
    keeper) dies, even by SIGKILL. Both fork from their only thread, so this fires exactly
    when the parent is gone."""
    if _LIBC is not None:
        _LIBC.prctl(PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)


def stop_group(proc: subprocess.Popen[bytes], sig: int = signal.SIGTERM) -> None:
    """Signal the guard's own process group (the command and everything it started; the
    guard ignores it), wait ``GRACE_S`` for the command, then SIGKILL it."""
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        os.killpg(os.getpgrp(), sig)
        proc.wait(GRACE_S)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(GRACE_S)
    except ProcessLookupError:
        pass


def supervise(parent: int, cmd: list[str]) -> int:
    if os.getsid(0) != os.getpid():
        os.setsid()  # a group of our own: signalling it never reaches the parent's group
    proc = subprocess.Popen(cmd, preexec_fn=die_with_parent)

    def forward(sig: int, _frame: FrameType | None) -> None:
        stop_group(proc, sig)
        sys.exit(proc.returncode if proc.returncode is not None else 128 + sig)

    signal.signal(signal.SIGTERM, forward)
    signal.signal(signal.SIGINT, forward)
    while True:
        try:
            return proc.wait(POLL_S)
        except subprocess.TimeoutExpired:
            pass
        if os.getppid() != parent:  # re-parented: whoever started us is gone
            stop_group(proc)
            return 0


def main(argv: list[str]) -> int:
    if len(argv) < 3 or argv[1] != "--":
        print(__doc__, file=sys.stderr)
        return 2
    return supervise(int(argv[0]), argv[2:])


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
