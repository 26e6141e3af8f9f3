"""The temporary Prefect server shared between calls (``flows/shared_server.py``, #26): a
second call finds the first call's server, a user holding the lease keeps it, and it stops
by itself once idle, leaving no process and no state behind."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

ATTACH = """
import json, os, sys, time
from v2xlake.flows import shared_server
t = time.perf_counter()
wait = shared_server.attach()
wait()
print(json.dumps([os.environ["PREFECT_API_URL"], time.perf_counter() - t]), flush=True)
time.sleep(float(sys.argv[1]))
"""


def _env(home: Path, idle: float) -> dict[str, str]:
    """A caller whose Prefect settings all come from ``home``: none of the suite's own
    (earlier tests put ``PREFECT_HOME`` and the API URL into this process's environment)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")}
    env.update(V2XLAKE_HOME=str(home), V2XLAKE_SERVER_IDLE_S=str(idle))
    env.pop("V2XLAKE_SHARED_SERVER", None)
    return env


def _attach(env: dict[str, str], hold: float = 0.0) -> tuple[str, float]:
    res = subprocess.run([sys.executable, "-c", ATTACH, str(hold)], env=env,
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    url, seconds = json.loads(res.stdout.strip().splitlines()[-1])
    return str(url), float(seconds)


def test_shared_server_reused_held_and_stopped_when_idle(tmp_path: Path) -> None:
    from v2xlake.flows import keeper, shared_server

    home = tmp_path / "home"
    env = _env(home, idle=3.0)
    state_file = home / "prefect" / keeper.STATE
    try:
        url, _ = _attach(env)  # starts it; the caller exits, the server stays
        keeper_pid = json.loads(state_file.read_text())["pid"]
        assert shared_server.healthy(url)
        again, _ = _attach(env)  # found, not started: the same URL and keeper
        assert again == url
        assert json.loads(state_file.read_text())["pid"] == keeper_pid
        # a user holding the lease keeps it past the idle time
        holder = subprocess.Popen([sys.executable, "-c", ATTACH, "8"], env=env,
                                  stdout=subprocess.PIPE, text=True)
        assert holder.stdout is not None
        assert json.loads(holder.stdout.readline())[0] == url
        time.sleep(6.0)
        assert shared_server.healthy(url), "stopped while a user held the lease"
        holder.wait(30)
        # idle: the keeper stops the server and removes its state
        deadline = time.monotonic() + 30
        while state_file.exists() and time.monotonic() < deadline:
            time.sleep(0.5)
        assert not state_file.exists()
        # the keeper drops the state first (a new user then starts a fresh server) and then
        # stops the server's process group: on a loaded machine that takes a moment
        def keeper_alive() -> bool:
            try:
                cmd = Path(f"/proc/{keeper_pid}/cmdline").read_text(errors="replace")
            except OSError:
                return False
            return "keeper.py" in cmd
        while keeper_alive() and time.monotonic() < deadline + 30:
            time.sleep(0.5)
        assert not keeper_alive()
        assert not shared_server.healthy(url)
    finally:
        shared_server.stop(home / "prefect")  # a failed assertion leaves nothing running


def test_shared_server_off_switch_and_user_url(monkeypatch: pytest.MonkeyPatch) -> None:
    """No shared server when the user names an API or switches it off."""
    from v2xlake.flows import shared_server

    monkeypatch.delenv("PREFECT_API_URL", raising=False)
    monkeypatch.setenv("V2XLAKE_SHARED_SERVER", "0")
    assert not shared_server.enabled() and shared_server.attach() is None
    monkeypatch.setenv("V2XLAKE_SHARED_SERVER", "1")
    monkeypatch.setenv("PREFECT_API_URL", "http://127.0.0.1:9/api")
    assert not shared_server.enabled()
    monkeypatch.delenv("PREFECT_API_URL")
    assert shared_server.enabled()
