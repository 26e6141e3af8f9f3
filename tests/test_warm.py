"""The warm process (``flows/warm.py``, #26): a CLI call it runs behaves as the same call run
in its own process (output, exit status, files relative to the caller's folder), signals
reach the call, a killed warm process or changed code means the call runs in-process.

The package is copied into the test's folder, so that the stale-code test can change a
file without touching the repository; the warm process imports that copy."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
CLI = [sys.executable, "-m", "v2xlake.flows.cli"]
START = ("import os, sys; from v2xlake.flows import warm; "
         "warm.start(warm._home(), warm.identity(), dict(os.environ), sys.path)")

pytestmark = pytest.mark.slow


@dataclass
class Warm:
    env: dict[str, str]  # a caller that the warm process serves
    home: Path  # its PREFECT_HOME
    src: Path  # the package copy it imported
    work: Path  # the callers' folder

    @property
    def log(self) -> Path:
        return self.home / "warm.log"

    def calls(self) -> list[int]:
        """Pids of the calls the warm process forked so far."""
        text = self.log.read_text() if self.log.exists() else ""
        return [int(m) for m in re.findall(r"call (\d+): (?!exit)", text)]

    def server_pid(self) -> int:
        return int(re.findall(r"warm\[(\d+)\] serving", self.log.read_text())[-1])

    def start(self) -> None:
        served = self.log.read_text().count("serving") if self.log.exists() else 0
        subprocess.run([sys.executable, "-c", START], env=self.env, cwd=self.work, check=True,
                       timeout=60)
        deadline = time.monotonic() + 300  # imports of Prefect and every stage, loaded host
        while time.monotonic() < deadline:
            if self.log.exists() and self.log.read_text().count("serving") > served:
                return
            time.sleep(0.5)
        raise AssertionError(f"no warm process:\n{self.log.read_text()[-3000:]}")

    def run(self, *argv: str, warm: bool = True) -> subprocess.CompletedProcess[str]:
        env = self.env if warm else dict(self.env, V2XLAKE_WARM="0")
        return subprocess.run([*CLI, *argv], env=env, cwd=self.work, capture_output=True,
                              text=True, timeout=300)


@pytest.fixture(scope="module")
def warm(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Warm]:
    root = tmp_path_factory.mktemp("warm")
    src = root / "src"
    shutil.copytree(REPO / "v2xlake", src / "v2xlake",
                    ignore=shutil.ignore_patterns("__pycache__"))
    env = {k: v for k, v in os.environ.items()
           if not k.startswith(("PREFECT_", "V2XLAKE_", "PYTEST_"))}
    env.update(V2XLAKE_HOME=str(root / "home"), V2XLAKE_WARM="1",
               V2XLAKE_SERVER_IDLE_S="120", COLUMNS="120",
               PYTHONPATH=os.pathsep.join([str(src), str(REPO / "tests")]))
    work = root / "work"
    work.mkdir()
    w = Warm(env, root / "home" / "prefect", src, work)
    w.start()
    yield w
    from v2xlake.flows import warm as warm_mod

    warm_mod.stop(w.home)


def _masked(text: str, name: str) -> str:
    """Output without what differs between two runs: timings and the clip's name."""
    return re.sub(r"\d+\.\d+ s\b", "T s", text.replace(name, "NAME"))


def test_warm_call_behaves_as_in_process(warm: Warm) -> None:
    before = len(warm.calls())
    cases = [["--version"],
             ["query", "select 1", "--lake", "no-such-lake"],  # relative: the caller's folder
             ["no-such-command"],
             ["process", "."],  # not a clip folder
             ["params", "show", "--stage", "qa"]]
    for argv in cases:
        hot, cold = warm.run(*argv), warm.run(*argv, warm=False)
        assert (hot.returncode, hot.stdout, hot.stderr) == \
            (cold.returncode, cold.stdout, cold.stderr), argv
    assert [warm.run(*a, warm=False).returncode for a in cases[1:4]] == [2, 2, 2]
    # a command that writes files, relative to the caller's folder
    made = {}
    for name, use_warm in (("clip_hot", True), ("clip_cold", False)):
        res = warm.run("simulate", name, "--seconds", "0.3", "--cameras", "0", "--seed", "3",
                       warm=use_warm)
        assert res.returncode == 0, res.stderr
        made[name] = (_masked(res.stdout, name), res.stderr,
                      sorted(str(p.relative_to(warm.work / name))
                             for p in (warm.work / name).rglob("*")))
        again = warm.run("simulate", name, "--seconds", "0.3", warm=use_warm)  # not empty: refused
        assert again.returncode == 2 and "not empty" in again.stderr
    assert made["clip_hot"] == made["clip_cold"]
    # every warm call above went through the warm process, none of the others
    assert len(warm.calls()) - before == len(cases) + 2


def _running(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def _long_call(warm: Warm, name: str) -> tuple[subprocess.Popen[str], int]:
    """A call that runs for a while (a long simulated clip), once its child has started."""
    before = warm.calls()
    proc = subprocess.Popen([*CLI, "simulate", name, "--seconds", "120", "--cameras", "0"],
                            env=warm.env, cwd=warm.work, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60
    while len(warm.calls()) == len(before) and time.monotonic() < deadline:
        time.sleep(0.1)
    child = warm.calls()[-1]
    time.sleep(2.0)  # into the work
    assert proc.poll() is None and _running(child), "the long call ended early"
    return proc, child


def _gone(pid: int, within: float = 20.0) -> bool:
    deadline = time.monotonic() + within
    while _running(pid) and time.monotonic() < deadline:
        time.sleep(0.1)
    return not _running(pid)


def test_signals_reach_the_call(warm: Warm) -> None:
    # Ctrl-C: the CLI's KeyboardInterrupt answer (130), as in its own process
    proc, child = _long_call(warm, "long_int")
    proc.send_signal(signal.SIGINT)
    assert proc.wait(60) == 130
    assert _gone(child)
    # SIGTERM: the call ends by it, and so does the client (Python's default)
    proc, child = _long_call(warm, "long_term")
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(60) == -signal.SIGTERM
    assert _gone(child)
    # the client SIGKILLed: its call goes with it
    proc, child = _long_call(warm, "long_kill")
    proc.kill()
    proc.wait(60)
    assert _gone(child)
    assert _running(warm.server_pid()), "the warm process itself must stay"


def test_killed_or_stale_warm_process_falls_back(warm: Warm) -> None:
    # killed: the call runs in-process, with the same answer
    os.kill(warm.server_pid(), signal.SIGKILL)
    before = len(warm.calls())
    res = warm.run("--version")
    assert res.returncode == 0 and res.stdout.startswith("v2xlake ")
    assert len(warm.calls()) == before
    # a fresh one, then the code changes under it: in-process again, and it exits
    warm.start()
    pid = warm.server_pid()
    assert warm.run("--version").returncode == 0 and len(warm.calls()) == before + 1
    changed = warm.src / "v2xlake" / "flows" / "demo.py"
    os.utime(changed, ns=(time.time_ns(), time.time_ns()))
    res = warm.run("--version")
    assert res.returncode == 0 and res.stdout.startswith("v2xlake ")
    assert len(warm.calls()) == before + 1
    assert _gone(pid, within=30.0)
    assert "code or installation changed" in warm.log.read_text()
    states = list(warm.home.glob("warm-*.json"))
    deadline = time.monotonic() + 10
    while states and time.monotonic() < deadline:  # the keeper drops its state
        time.sleep(0.2)
        states = [s for s in states if s.exists()]
    assert not states, [json.loads(s.read_text()) for s in states]


def test_warm_switch_and_verbose_stay_in_process(monkeypatch: pytest.MonkeyPatch) -> None:
    from v2xlake.flows import warm

    monkeypatch.setenv("V2XLAKE_WARM", "0")
    assert not warm.enabled() and warm.call(["--version"]) is None
    monkeypatch.setenv("V2XLAKE_WARM", "1")
    assert warm.enabled()
    assert warm._verbose(["-v", "process", "x"]) and not warm._verbose(["process", "-v"])
    assert warm.call(["-v", "--version"]) is None
