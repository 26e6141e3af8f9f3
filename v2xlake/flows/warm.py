"""The warm process: Prefect and the stages imported once, one forked child per CLI call.

WHY (#26, fixed cost of a real call): with the shared Prefect server (``flows/shared_server.py``)
a ``v2xlake process`` call still paid 5.7 s of imports (Prefect and every stage), ~2 s of
first use inside the stages (lazy imports of Open3D, SciPy, onnxruntime, ...) and a Python
start: a trivial 7-task Prefect flow alone costs ~4.8 s, so no in-process change meets 5 % of
a 10 s clip (~4.9 s). This module keeps one process per (code, interpreter, environment)
with those modules imported, and runs each CLI call in a ``fork`` of it:

* **client** (``call``, from ``cli.main`` when it is the program's entry): takes a shared
  lock on the lease, connects to ``$PREFECT_HOME/warm-<identity>.sock`` and sends its argv,
  environment, working folder, umask and ``sys.path`` with its stdin/stdout/stderr file
  descriptors (``SCM_RIGHTS``); gets the child's pid, forwards the signals it receives
  (Ctrl-C: SIGINT to the child's process group, as a terminal does; SIGTERM to the child;
  Ctrl-Z stops both), and ends with the child's exit status (a child killed by a signal: the
  client kills itself with the same signal). Whenever no warm process of its identity
  answers, it returns None and the CLI runs in-process, as before; such a call that ran
  Prefect starts one, detached, when it is done (``start_if_wanted``).
* **warm process** (``serve``): imports Prefect, the CLI, the flows and every stage, then the
  modules earlier calls imported lazily (``warm-modules.json``, learned from the calls: only
  modules inside the trees the identity covers), and refuses to serve if any of that
  started a Python thread. For each request it forks a child that waits for the client's
  go (so a client that gives up before it can fall back without running anything twice),
  takes the descriptors as 0/1/2, the environment, folder, umask and ``sys.path``, and runs
  ``cli.main(argv)`` then the interpreter's exit steps (atexit). The parent reaps children
  and sends each exit status; a client that disappears (even SIGKILLed) gets its child's
  process group SIGKILLed.
* **staleness**: the identity hashes the interpreter, every file of the v2xlake package
  (path, size, mtime), the ``sys.path`` folders' mtimes (an install changes them) and the
  environment (without a few per-terminal variables): another code version or environment
  maps to another socket, so a stale process is never used; one whose code changed on
  disk exits at its next idle check.
* **lifecycle**: ``flows/keeper.py`` as for the shared server (detached, lease, stops
  ``V2XLAKE_SERVER_IDLE_S`` after its last call, or when its home folder is deleted).

Forking a process that imported NumPy, SciPy, OpenCV, pyarrow and duckdb: those start native
threads at import (OpenBLAS pools with ``pthread_atfork`` handlers, jemalloc's background
thread, reset in a child, and duckdb's idle scheduler thread); none holds a lock while the
warm process waits in ``select``, and the children run every stage (``tests/test_warm.py``,
``tests/bench/bench_fixed.py``). Prefect starts no thread at import; its threads start in the
children.

``V2XLAKE_WARM=0`` switches it off (the test-suite does, unless a test asks for it); calls with
``-v`` run in-process (Prefect's logging is configured at import). Only the standard library
is imported on the client path.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import importlib
import json
import os
import select
import signal
import socket
import struct
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from types import FrameType
from typing import Any

from v2xlake.flows import keeper
from v2xlake.flows.guard import alive

NAME = "warm"
PACKAGE = Path(__file__).resolve().parents[1]
LEARNED = "warm.modules.json"  # not "warm-*.json": those are state files
CONNECT_TIMEOUT_S = 10.0  # the warm process answers a request in milliseconds
TICK_S = 2.0  # how often an idle warm process checks its code and the learned modules
MAX_SOCKET_PATH = 100  # bytes; AF_UNIX allows 107
# variables that differ between terminals of one user and are read at run time only (the
# child gets the caller's whole environment): not part of the identity
VOLATILE = ("PWD", "OLDPWD", "SHLVL", "_", "COLUMNS", "LINES", "TERM", "COLORTERM",
            "TERM_PROGRAM", "TERM_PROGRAM_VERSION", "TERM_SESSION_ID", "WINDOWID", "TMUX_PANE",
            "SSH_CLIENT", "SSH_CONNECTION", "SSH_TTY", "SSH_AUTH_SOCK", "PS1", "PS2", "PS4",
            "PROMPT_COMMAND", "PYTEST_CURRENT_TEST")
# imported before any learned module: what every `process` call needs
CORE = ("prefect", "prefect.flow_engine", "prefect.task_engine", "prefect.futures",
        "prefect.artifacts", "prefect.client.orchestration", "v2xlake.flows.cli",
        "v2xlake.flows.pipeline", "v2xlake.flows.noop", "v2xlake.flows.params",
        "v2xlake.flows.runners", "v2xlake.flows.shared_server", "v2xlake.flows.server",
        "v2xlake.flows.bookkeeping")
# signals the client passes on: terminal-generated ones to the child's process group (as
# the terminal would have sent them to the in-process CLI's group), the others to the child
TO_GROUP = (signal.SIGINT, signal.SIGHUP, signal.SIGQUIT)
TO_CHILD = (signal.SIGTERM, signal.SIGUSR1, signal.SIGUSR2)
_OFF = ("0", "false", "no", "off")


def enabled() -> bool:
    return os.environ.get("V2XLAKE_WARM", "1").lower() not in _OFF


def _home() -> Path:
    """``PREFECT_HOME`` as ``settings.configure_prefect`` sets it (without changing the
    environment: the client runs before the CLI configures anything)."""
    from v2xlake.flows.settings import v2xlake_home

    return Path(os.environ.get("PREFECT_HOME") or v2xlake_home() / "prefect").expanduser()


def _verbose(argv: list[str]) -> bool:
    """``-v`` before the command: Prefect's logging would differ from the warm process's."""
    for a in argv:
        if not a.startswith("-"):
            return False
        if a in ("-v", "--verbose"):
            return True
    return False


def code_stamp(path: list[str]) -> list[Any]:
    """Every file of the package (not ``__pycache__``: numba's caches change there) and the
    mtime of every ``sys.path`` folder after the first (site-packages: an install or
    uninstall changes it); ~2 ms."""
    files: list[Any] = []
    for root, dirs, names in os.walk(PACKAGE):
        dirs[:] = sorted(d for d in dirs if d != "__pycache__")
        for n in sorted(names):
            with contextlib.suppress(OSError):
                st = os.stat(os.path.join(root, n))
                files.append([root, n, st.st_size, st.st_mtime_ns])
    for p in path[1:]:
        with contextlib.suppress(OSError):
            files.append([p, os.stat(p or ".").st_mtime_ns])
    return files


def identity(env: dict[str, str] | None = None, path: list[str] | None = None) -> str:
    """What a warm process must share with a caller to run its call as the caller would
    (``env``, ``path``: the caller's, by default this process's)."""
    env = dict(os.environ if env is None else env)
    for k in VOLATILE:
        env.pop(k, None)
    path = list(sys.path if path is None else path)
    data = [sys.executable, sys.version, os.getuid(), str(PACKAGE), path[1:],
            sorted(env.items()), code_stamp(path)]
    return hashlib.sha256(json.dumps(data).encode()).hexdigest()[:20]


def _failed(home: Path, ident: str) -> Path:
    """Marks an identity whose warm process refused to serve: never started again."""
    return home / f"{NAME}-{ident}.failed"


def _paths(home: Path, ident: str) -> tuple[Path, Path, Path]:
    """Socket, lease and state file of the warm process of ``ident``."""
    base = f"{NAME}-{ident}"
    return home / f"{base}.sock", home / f"{base}.lease", home / f"{base}.json"


# ------------------------------------------------------------------------------- client
@dataclass
class _Want:
    home: Path
    ident: str
    env: dict[str, str]
    path: list[str]
    ran_prefect: bool = False


_want: _Want | None = None  # set by a call that fell back: start one if it ran Prefect


def note_prefect_call() -> None:
    """``run_process`` is about to start Prefect: a fallen-back call starts a warm process
    when it ends (a call answered by the no-op check does not: it needs none)."""
    if _want is not None:
        _want.ran_prefect = True


def call(argv: list[str]) -> int | None:
    """Run the CLI call ``argv`` in a warm process; None when none answers (run in-process)."""
    global _want
    if not enabled() or _verbose(argv):
        return None
    home = _home()
    ident = identity()
    sock_path, lease, _ = _paths(home, ident)
    _want = _Want(home, ident, dict(os.environ), list(sys.path))
    if len(os.fsencode(sock_path)) > MAX_SOCKET_PATH or not sock_path.exists():
        return None
    lease_fd = keeper.hold_lease(lease)
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    try:
        sock.settimeout(CONNECT_TIMEOUT_S)
        umask = os.umask(0)
        os.umask(umask)
        request = {"identity": ident, "argv": list(sys.argv[:1]) + argv, "env": dict(os.environ),
                   "cwd": os.getcwd(), "umask": umask, "path": list(sys.path)}
        sock.connect(os.fspath(sock_path))
        socket.send_fds(sock, [json.dumps(request).encode()], [0, 1, 2])
        reply = json.loads(sock.recv(1 << 16) or b"{}")
        pid = int(reply["pid"])
    except (OSError, ValueError, KeyError, TypeError):
        # nothing ran: the child (if any) waits for our go and ends on our close
        sock.close()
        os.close(lease_fd)
        return None
    _want = None
    try:
        return _wait(sock, pid)
    finally:
        with contextlib.suppress(OSError):
            os.utime(lease_fd)  # idle counts from the end of the last call
        os.close(lease_fd)
        sock.close()


@contextlib.contextmanager
def _forwarding(pid: int) -> Iterator[None]:
    """Pass the client's signals on to the child while it runs."""
    def forward(sig: int, _frame: FrameType | None) -> None:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            if sig in TO_GROUP:
                os.killpg(pid, sig)
            else:
                os.kill(pid, sig)

    def stop(sig: int, _frame: FrameType | None) -> None:  # Ctrl-Z: stop both
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(pid, signal.SIGTSTP)
        signal.signal(signal.SIGTSTP, signal.SIG_DFL)
        os.kill(os.getpid(), signal.SIGTSTP)  # stopped here until SIGCONT
        signal.signal(signal.SIGTSTP, stop)

    def cont(sig: int, _frame: FrameType | None) -> None:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(pid, signal.SIGCONT)

    handlers = {s: forward for s in (*TO_GROUP, *TO_CHILD)}
    handlers.update({signal.SIGTSTP: stop, signal.SIGCONT: cont})
    old = {s: signal.signal(s, h) for s, h in handlers.items()}
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def _wait(sock: socket.socket, pid: int) -> int:
    with _forwarding(pid):
        sock.settimeout(None)
        sock.send(b"go")
        data = b""
        with contextlib.suppress(OSError):
            data = sock.recv(1 << 16)
    try:
        status = int(json.loads(data)["exit"])
    except (ValueError, KeyError, TypeError):
        sys.stderr.write("v2xlake: the warm process ended during the call (see "
                         f"{_home() / 'warm.log'}); its result is unknown\n")
        return 1
    if status < 0:  # killed by a signal: end the same way, as the in-process CLI would
        sys.stdout.flush()
        sys.stderr.flush()
        signal.signal(-status, signal.SIG_DFL)
        os.kill(os.getpid(), -status)
        return 128 - status
    return status


def _learnable(name: str, mod: Any, roots: tuple[str, ...]) -> bool:
    """A module the warm process may import ahead: one whose file lies in a tree the
    identity covers (the package, the interpreter's prefixes), so a preloaded copy is never
    older than the file a fresh process would read."""
    f = getattr(mod, "__file__", None)
    return (isinstance(f, str) and not name.startswith("__main__")
            and os.path.realpath(f).startswith(roots))


def learn_modules(home: Path, known: set[str] | None = None) -> None:
    """Add this process's imported modules (those not in ``known``) to the learned list."""
    roots = tuple(os.path.realpath(p) + os.sep for p in
                  {str(PACKAGE), sys.prefix, sys.base_prefix, sys.exec_prefix})
    known = known or set()
    new = {n for n, m in list(sys.modules.items()) if n not in known and _learnable(n, m, roots)}
    if not new:
        return
    file = home / LEARNED
    try:
        old = set(json.loads(file.read_text()))
    except (OSError, ValueError, TypeError):
        old = set()
    if new <= old:
        return
    tmp = file.with_name(f"{LEARNED}.{os.getpid()}")
    with contextlib.suppress(OSError):
        tmp.write_text(json.dumps(sorted(old | new)))
        os.replace(tmp, file)


def start_if_wanted() -> None:
    """After an in-process call that ran Prefect: learn its modules and start the warm
    process of its identity, detached, unless one runs or is starting."""
    want = _want
    if want is None or not want.ran_prefect:
        return
    with contextlib.suppress(OSError):
        learn_modules(want.home)
        start(want.home, want.ident, want.env, want.path)


def start(home: Path, ident: str, env: dict[str, str], path: list[str]) -> int | None:
    """The warm process under its keeper, recorded in its state file; returns the keeper's
    pid, or None when one is already recorded and alive (starts are serialised by a lock)."""
    sock_path, _, state = _paths(home, ident)
    if len(os.fsencode(sock_path)) > MAX_SOCKET_PATH or _failed(home, ident).exists():
        return None
    home.mkdir(parents=True, exist_ok=True)
    lock = os.open(home / f"{NAME}-{ident}.start.lock", os.O_RDWR | os.O_CREAT, 0o600)
    try:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if (pid := keeper.state_pid(state)) is not None and alive(pid):
            return None
        from v2xlake.flows.shared_server import idle_seconds

        code = ("import sys, json; sys.path[:] = json.loads(sys.argv[1]); "
                "from v2xlake.flows.warm import main; sys.exit(main(sys.argv[2:]))")
        cmd = [sys.executable, "-c", code, json.dumps([p or os.getcwd() for p in path]),
               str(home), ident]
        with open(home / f"{NAME}.log", "ab") as log:
            proc = subprocess.Popen(
                [sys.executable, str(Path(keeper.__file__).resolve()), str(home),
                 str(idle_seconds()), f"{NAME}-{ident}", "--", *cmd],
                env=env, cwd=home, stdin=subprocess.DEVNULL, stdout=log,
                stderr=subprocess.STDOUT, start_new_session=True, close_fds=True)
        keeper.write_state(state, {"pid": proc.pid, "socket": str(sock_path),
                                   "started": time.time()})
        return proc.pid
    finally:
        os.close(lock)


def stop(home: Path | None = None) -> int:
    """Stop every warm process of ``home`` (tests, a user who wants them gone): SIGTERM its
    keeper, which stops it and removes its state. Returns how many were running."""
    home = home or _home()
    n = 0
    for state in home.glob(f"{NAME}-*.json"):
        pid = keeper.state_pid(state)
        if pid is not None and alive(pid):
            with contextlib.suppress(OSError):  # gone meanwhile
                os.kill(pid, signal.SIGTERM)
                n += 1
    return n


# ------------------------------------------------------------------------- warm process
def _log(text: str) -> None:
    sys.stderr.write(f"{time.strftime('%Y-%m-%d %H:%M:%S')} warm[{os.getpid()}] {text}\n")
    sys.stderr.flush()


def _preload(home: Path) -> set[str]:
    """Import the core modules, every stage and the learned ones; returns what was learned."""
    from v2xlake.flows.settings import configure_prefect

    configure_prefect(quiet=True)  # as the CLI does before Prefect is imported
    for name in CORE:
        importlib.import_module(name)
    from v2xlake.flows.stage_names import STAGE_NAMES, registry_stage

    for stage in STAGE_NAMES:
        registry_stage(stage)
    learned = _import_learned(home)
    _log(f"numba overloads loaded from their caches: {_load_numba_caches()}")
    return learned


def _load_numba_caches() -> int:
    """Load the package's numba functions from their on-disk caches now, once, instead of
    in every call's stages (~0.1 s each on first use: 0.8 s for the 8 cached overloads of a
    camera-less clip). Only entries whose key still matches (same signature, CPU and
    source) are loaded, so nothing is compiled here; no numba thread is started (no
    ``parallel=True`` kernel is run). Numba internals: any error just skips the warm-up.
    Returns how many overloads were loaded."""
    try:
        from numba.core.dispatcher import Dispatcher
    except ImportError:
        return 0
    loaded = 0
    for name, mod in list(sys.modules.items()):
        if not name.startswith("v2xlake."):
            continue
        for obj in list(vars(mod).values()):
            cache: Any = getattr(obj, "_cache", None)
            if not isinstance(obj, Dispatcher) or cache is None:
                continue
            try:
                codegen = getattr(obj, "targetctx").codegen()  # noqa: B009 - untyped
                for key in cache._cache_file._load_index():
                    if cache._index_key(key[0], codegen) == key:
                        obj.compile(key[0])
                        loaded += 1
            except Exception:  # a numba version without these internals: no warm-up
                continue
    return loaded


def _import_learned(home: Path) -> set[str]:
    try:
        names = json.loads((home / LEARNED).read_text())
    except (OSError, ValueError, TypeError):
        return set()
    for name in names:
        if name not in sys.modules:
            try:
                importlib.import_module(name)
            except (Exception, SystemExit):  # one that will not import ahead: not preloaded
                continue
    return set(names)


@dataclass
class _Call:
    conn: socket.socket
    gate: int | None  # write end of the child's go pipe, until the client says go
    since: float


def _peer_uid(conn: socket.socket) -> int:
    creds = conn.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, struct.calcsize("3i"))
    return int(struct.unpack("3i", creds)[1])


def serve(home: Path, ident: str) -> int:
    """The warm process's loop (single-threaded: it forks)."""
    sock_path, _, _ = _paths(home, ident)
    env, path = dict(os.environ), list(sys.path)  # the caller's (imports may change them)
    if identity(env, path) != ident:  # the code changed between the caller's look and now
        _log("stale at start")
        return 0
    t0 = time.perf_counter()
    learned = _preload(home)
    import threading

    if threading.active_count() != 1:  # a fork would lose a running Python thread
        _log(f"not serving: imports started threads {threading.enumerate()}")
        _failed(home, ident).touch()  # not started again for this identity
        return 3
    modules_mtime = _mtime(home / LEARNED)
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    with contextlib.suppress(FileNotFoundError):
        sock_path.unlink()
    old_umask = os.umask(0o177)
    try:
        listener.bind(os.fspath(sock_path))
    finally:
        os.umask(old_umask)
    listener.listen(64)
    inode = sock_path.stat().st_ino
    _log(f"serving {ident} after {time.perf_counter() - t0:.1f} s of imports "
         f"({len(sys.modules)} modules)")
    wake_r, wake_w = os.pipe()
    os.set_blocking(wake_r, False)
    os.set_blocking(wake_w, False)
    signal.set_wakeup_fd(wake_w)
    signal.signal(signal.SIGCHLD, lambda *_: None)
    calls: dict[int, _Call] = {}
    last_check = time.monotonic()
    try:
        while True:
            watched: list[Any] = [listener, wake_r, *(c.conn for c in calls.values())]
            ready = select.select(watched, [], [], TICK_S)[0]
            if wake_r in ready:
                with contextlib.suppress(BlockingIOError):
                    os.read(wake_r, 4096)
            _reap(calls)
            for pid, c in list(calls.items()):
                if c.conn in ready:
                    _client_says(pid, c)
            if listener in ready:
                _accept(listener, ident, calls, [listener.fileno(), wake_r, wake_w])
            if not calls and time.monotonic() - last_check > TICK_S:
                last_check = time.monotonic()
                if identity(env, path) != ident:
                    _log("code or installation changed: exiting")
                    return 0
                if _mtime(home / LEARNED) != modules_mtime:
                    modules_mtime = _mtime(home / LEARNED)
                    learned = _import_learned(home)
                    if threading.active_count() != 1:
                        _log(f"learned imports started threads: exiting "
                             f"{threading.enumerate()}")
                        _failed(home, ident).touch()
                        return 3
            if not sock_path.exists() or sock_path.stat().st_ino != inode:
                _log("socket removed: exiting")
                return 0
    finally:
        with contextlib.suppress(OSError):
            if sock_path.stat().st_ino == inode:
                sock_path.unlink()
        del learned


def _mtime(p: Path) -> int:
    try:
        return p.stat().st_mtime_ns
    except OSError:
        return 0


def _reap(calls: dict[int, _Call]) -> None:
    while True:
        try:
            pid, status = os.waitpid(-1, os.WNOHANG)
        except ChildProcessError:
            return
        if pid == 0:
            return
        c = calls.pop(pid, None)
        if c is None:
            continue
        _log(f"call {pid}: exit {os.waitstatus_to_exitcode(status)} after "
             f"{time.monotonic() - c.since:.1f} s")
        with contextlib.suppress(OSError):
            c.conn.send(json.dumps({"exit": os.waitstatus_to_exitcode(status)}).encode())
        _close(c)


def _close(c: _Call) -> None:
    c.conn.close()
    if c.gate is not None:
        with contextlib.suppress(OSError):
            os.close(c.gate)
        c.gate = None


def _client_says(pid: int, c: _Call) -> None:
    try:
        data = c.conn.recv(64)
    except OSError:
        data = b""
    if data == b"go" and c.gate is not None:
        os.write(c.gate, b"1")
        os.close(c.gate)
        c.gate = None
    elif not data:  # the client is gone (killed): its call goes with it
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(pid, signal.SIGKILL)
        c.conn.close()
        c.conn = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)  # never readable
        if c.gate is not None:
            with contextlib.suppress(OSError):
                os.close(c.gate)
            c.gate = None


def _accept(listener: socket.socket, ident: str, calls: dict[int, _Call],
            own: list[int]) -> None:
    conn, _ = listener.accept()
    fds: list[int] = []
    try:
        conn.settimeout(5.0)
        if _peer_uid(conn) != os.getuid():
            conn.close()
            return
        data, fds, _, _ = socket.recv_fds(conn, 1 << 20, 8)
        req = json.loads(data)
        if req.get("identity") != ident or len(fds) != 3:
            conn.send(json.dumps({"stale": True}).encode())
            raise ValueError("stale or malformed request")
    except (OSError, ValueError):
        for fd in fds:
            os.close(fd)
        conn.close()
        return
    gate_r, gate_w = os.pipe()
    sys.stdout.flush()
    sys.stderr.flush()
    parent = os.getpid()
    pid = os.fork()
    if pid == 0:  # the child: never returns
        code = 70
        try:
            close = [*own, gate_w, *(x for c in calls.values()
                                     for x in (c.conn.fileno(), c.gate) if x is not None)]
            code = _child(req, fds, conn, gate_r, close, parent)
        finally:
            os._exit(code)
    os.close(gate_r)
    for fd in fds:
        os.close(fd)
    _log(f"call {pid}: {' '.join(req['argv'][1:3])} ...")
    calls[pid] = _Call(conn, gate_w, time.monotonic())
    try:
        conn.settimeout(None)
        conn.send(json.dumps({"pid": pid}).encode())
    except OSError:  # the client left: the child sees its gate close and ends
        _close(calls[pid])
        calls[pid].conn = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)


def _child(req: dict[str, Any], fds: list[int], conn: socket.socket, gate: int,
           close: list[int], parent: int) -> int:
    """Become the caller's CLI process and run its call; returns the exit status."""
    os.setpgid(0, 0)  # a group of its own: the client signals it as a terminal would
    from v2xlake.flows.guard import die_with_parent

    die_with_parent()  # the warm process forked from its only thread: exact
    if os.getppid() != parent:
        return 1
    signal.set_wakeup_fd(-1)
    for s in (signal.SIGCHLD, signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT, signal.SIGUSR1,
              signal.SIGUSR2, signal.SIGTSTP, signal.SIGCONT):
        signal.signal(s, signal.SIG_DFL)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    conn.close()
    for fd in close:
        with contextlib.suppress(OSError):
            os.close(fd)
    go = os.read(gate, 1)
    os.close(gate)
    if go != b"1":  # the client gave up before its go: it runs the call itself
        return 0
    for target, fd in enumerate(fds):
        os.dup2(fd, target)
    for fd in fds:
        if fd > 2:
            os.close(fd)
    os.chdir(req["cwd"])
    os.umask(int(req["umask"]))
    os.environ.clear()
    os.environ.update(req["env"])
    sys.argv = list(req["argv"])
    sys.path[:] = req["path"]
    for stream, fd in ((sys.stdout, 1), (sys.stderr, 2)):
        with contextlib.suppress(AttributeError, OSError, ValueError):
            stream.reconfigure(line_buffering=fd == 2 or os.isatty(fd))  # type: ignore[union-attr]
    if "numpy" in sys.modules:  # a fresh process seeds NumPy's global generator anew
        sys.modules["numpy"].random.seed()
    known = set(sys.modules)
    from v2xlake.flows import cli

    code = 1
    try:
        code = cli.main(sys.argv[1:])
    except SystemExit as e:
        code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
        if not isinstance(e.code, int | None):
            sys.stderr.write(f"{e.code}\n")
    except BaseException:
        sys.excepthook(*sys.exc_info())
        code = 1
    with contextlib.suppress(Exception):
        learn_modules(_home(), known)
    return _exit_steps(code)


def _exit_steps(code: int) -> int:
    """What the interpreter does at exit: wait for non-daemon threads, atexit, flush."""
    import atexit
    import threading

    with contextlib.suppress(Exception):
        threading._shutdown()  # type: ignore[attr-defined]
    with contextlib.suppress(Exception):
        atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    return code


def main(argv: list[str]) -> int:
    """``python -c ... HOME IDENTITY`` (``start``): the warm process under its keeper."""
    if len(argv) != 2:
        print(__doc__, file=sys.stderr)
        return 2
    return serve(Path(argv[0]), argv[1])
