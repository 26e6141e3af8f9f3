"""Fixed cost of a real ``v2xlake process`` call, where it goes, and its share of a 10 s clip.

    python tests/bench/bench_fixed.py [--work DIR] [--repeat 3] [--modes temporary,shared,url,warm]

A real call (every stage runs: a fresh lake each time) on a small 1 s camera-less clip, each
a fresh process timed from its start to its exit. Its fixed cost is the call's wall time
minus the stages' own time (the ``seconds`` each stage reports: the work between its
manifest check and its manifest). Split, from a timeline recorded inside the call (the CLI's
progress display replaced by a recorder, the Prefect server's wait wrapped):

* ``interpreter + exit``: the process's wall time outside ``main`` (Python start, and at exit
  Prefect's log flush and the stop of a per-process temporary server);
* ``CLI imports``: ``v2xlake.flows.cli`` (typer, rich);
* ``server wait``: time blocked waiting for the Prefect server to answer;
* ``imports, params``: the rest up to the first flow (``import prefect``, every stage's
  module, the manifest check that answers no-ops);
* ``flow runs``: ``process-clips`` and ``process-clip`` created and started, up to the first
  stage task (clip sweep, params, the progress artifact);
* ``per task``: each stage task's wall time minus the stage's own seconds (task run created,
  its states, the manifest key and clip lock, the result), summed over the 7 stages;
* ``tail``: after the last stage (catalog refresh, artifacts, flows finishing).

Every row also gets the coarser split the warm row can be given (from the progress lines the
CLI prints on stderr): ``outside the flows`` (process start and exit, imports, the no-op
check, the server, the tail; for the warm row also the client and the fork) and ``flows and
tasks`` (flow-run creation and each task's overhead).

Modes: ``temporary``: Prefect's per-process temporary server (``V2XLAKE_SHARED_SERVER=0``,
what every call paid before); ``shared``: the temporary server shared between calls
(``flows/shared_server.py``), warm (started by a call before the measured ones);
``url``: ``PREFECT_API_URL`` naming a running ``prefect server``; ``warm``: the real command
line (``python -m v2xlake.flows.cli process CLIP --lake LAKE --format json``) run by the warm
process (``flows/warm.py``, started by an in-process call before the measured ones; each
measured call is checked to have gone through it), with the shared server: its fixed cost is
its wall time minus the stages' seconds from the JSON, and it is not split. The anchor, a
trivial Prefect flow of the same shape (tests/trivial_flow.py, 7 tasks), runs against the same
server in the same mode. The reference is the processing time of a 10 s camera-less simulated clip
(preset small, the stages' seconds summed, one shared-mode call on a fresh lake).
Not run by pytest.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
sys.path[:0] = [str(REPO)]

# runs inside the measured process: the CLI's `process`, with a recorder for its progress
CALL = r"""
import json, sys, time
T0 = time.perf_counter()
marks = {}
from v2xlake.flows import cli, server, shared_server
marks["cli_imported"] = time.perf_counter()
waits = []

def timed_wait(w):
    if w is None:
        return None
    def wait():
        t = time.perf_counter(); w(); waits.append(time.perf_counter() - t)
    return wait

_attach, _prestart = shared_server.attach, server.prestart_temporary_server
shared_server.attach = lambda: timed_wait(_attach())
server.prestart_temporary_server = lambda: timed_wait(_prestart())
events = []

class Recorder:
    def __init__(self, total, console, live=None):
        pass
    def __enter__(self):
        marks["flows_start"] = time.perf_counter(); return self
    def __exit__(self, *exc):
        marks["flows_end"] = time.perf_counter()
    def __call__(self, event):
        events.append((time.perf_counter(), event))

cli.StageProgress = Recorder
res = cli.run_process([sys.argv[1]], sys.argv[2])
marks["done"] = time.perf_counter()
stages = res[0]["stages"]
assert all(o["status"] != "cached" for o in stages), stages
starts = [t for t, e in events if e["event"] == "stage_start"]
ends = [t for t, e in events if e["event"] == "stage_end"]
own = sum(float(o["seconds"]) for o in stages)
print(json.dumps({
    "main": marks["done"] - T0, "cli_imports": marks["cli_imported"] - T0,
    "server_wait": sum(waits),
    "before_flows": marks["flows_start"] - marks["cli_imported"] - sum(waits),
    "flow_runs": starts[0] - marks["flows_start"],
    "per_task": sum(e - s for s, e in zip(starts, ends)) - own,
    "between": sum(s - e for e, s in zip(ends, starts[1:])),
    "tail": marks["done"] - ends[-1], "stages": own}))
"""

PARTS = ("interpreter + exit", "CLI imports", "server wait", "imports, params", "flow runs",
         "per task", "between tasks", "tail")
# the warm row's split, from the progress lines the CLI prints on stderr (not a terminal):
# the last line's time stamp counts from the progress display's start, just before the flows
WARM_PARTS = ("outside the flows", "flows and tasks")
PROGRESS = re.compile(r"^\[\s*([0-9.]+) s\] \d+/\d+ ", re.MULTILINE)


def _env(home: Path, mode: str, url: str | None) -> dict[str, str]:
    env = dict(os.environ, PYTHONPATH=str(REPO), V2XLAKE_HOME=str(home),
               PREFECT_HOME=str(home / "prefect"))
    env.pop("PREFECT_API_URL", None)
    env["V2XLAKE_SHARED_SERVER"] = "0" if mode == "temporary" else "1"
    env["V2XLAKE_WARM"] = "1" if mode == "warm" else "0"
    if mode == "url" and url:
        env["PREFECT_API_URL"] = url
    return env


def simulate(work: Path, name: str, seconds: float) -> Path:
    d = work / name
    if not (d / "clip.yaml").exists():
        shutil.rmtree(d, ignore_errors=True)
        subprocess.run([sys.executable, "-m", "v2xlake.flows.cli", "simulate", str(d),
                        "--seconds", str(seconds), "--seed", "5", "--cameras", "0",
                        "--clip-id", name], check=True, env=dict(os.environ,
                                                                 PYTHONPATH=str(REPO)),
                       cwd=REPO, capture_output=True)
    return d


def real_call(clip: Path, lake: Path, env: dict[str, str]) -> dict[str, float]:
    shutil.rmtree(lake, ignore_errors=True)
    t0 = time.perf_counter()
    res = subprocess.run([sys.executable, "-c", CALL, str(clip), str(lake)], env=env,
                         cwd=REPO, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if res.returncode != 0:
        raise RuntimeError(f"call failed:\n{res.stdout[-2000:]}\n{res.stderr[-3000:]}")
    r = json.loads(res.stdout.strip().splitlines()[-1])
    return {"wall": wall, "fixed": wall - r["stages"], "stages": r["stages"],
            "interpreter + exit": wall - r["main"], "CLI imports": r["cli_imports"],
            "server wait": r["server_wait"], "imports, params": r["before_flows"],
            "flow runs": r["flow_runs"], "per task": r["per_task"],
            "between tasks": r["between"], "tail": r["tail"]}


def _warm_calls(home: Path) -> int:
    """Calls the warm processes of ``home`` finished (their log's exit lines)."""
    try:
        text = (home / "prefect" / "warm.log").read_text()
    except OSError:
        return 0
    return sum(": exit " in line for line in text.splitlines())


def cli_call(clip: Path, lake: Path, env: dict[str, str]) -> dict[str, float]:
    """The real command line, timed from the client's start to its exit."""
    shutil.rmtree(lake, ignore_errors=True)
    t0 = time.perf_counter()
    res = subprocess.run([sys.executable, "-m", "v2xlake.flows.cli", "process", str(clip),
                          "--lake", str(lake), "--format", "json"], env=env, cwd=REPO,
                         capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if res.returncode != 0:
        raise RuntimeError(f"call failed:\n{res.stdout[-2000:]}\n{res.stderr[-3000:]}")
    stages = json.loads(res.stdout)[0]["stages"]
    assert all(o["status"] != "cached" for o in stages), stages
    own = sum(float(o["seconds"]) for o in stages)
    last = float(PROGRESS.findall(res.stderr)[-1])
    return {"wall": wall, "fixed": wall - own, "stages": own,
            "outside the flows": wall - last, "flows and tasks": last - own}


def warm_call(clip: Path, lake: Path, env: dict[str, str], home: Path) -> dict[str, float]:
    """``cli_call`` that must have been run by the warm process."""
    before = _warm_calls(home)
    r = cli_call(clip, lake, env)
    if _warm_calls(home) != before + 1:
        raise RuntimeError("the call did not go through the warm process (did the code "
                           f"change meanwhile? see {home / 'prefect' / 'warm.log'})")
    return r


def start_warm(clip: Path, lake: Path, env: dict[str, str], home: Path) -> None:
    """An in-process call that starts the warm process, then wait until it serves."""
    log = home / "prefect" / "warm.log"
    served = log.read_text().count(" serving ") if log.exists() else 0
    cli_call(clip, lake, env)
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline:
        if log.exists() and log.read_text().count(" serving ") > served:
            return
        time.sleep(0.5)
    raise RuntimeError(f"no warm process came up; see {log}")


def anchor(env: dict[str, str]) -> float:
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-c", "from trivial_flow import trivial_clip_flow; "
                    "trivial_clip_flow()"], env=dict(env, PYTHONPATH=os.pathsep.join(
                        [str(REPO), str(REPO / "tests")])), cwd=REPO, check=True,
                   capture_output=True)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "v2x-bench-fixed")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--modes", default="temporary,shared,url")
    ap.add_argument("--reference-seconds", type=float, default=10.0)
    args = ap.parse_args()
    work = args.work.resolve()
    work.mkdir(parents=True, exist_ok=True)
    home = work / "home"
    os.environ["V2XLAKE_HOME"] = str(home)  # before anything reads it (configure_prefect)
    os.environ["PREFECT_HOME"] = str(home / "prefect")
    from v2xlake.flows import shared_server
    from v2xlake.flows.server import start_server

    small = simulate(work, "fixed_small", 1.0)
    big = simulate(work, "fixed_ref", args.reference_seconds)
    modes = args.modes.split(",")
    server = start_server(work / "server") if "url" in modes else None
    try:
        # warm-up (not measured): numba caches, the checksum cache, the shared server
        real_call(small, work / "lake", _env(home, "shared", None))
        rows: dict[str, dict[str, float]] = {}
        for mode in modes:
            env = _env(home, mode, server.api_url if server else None)
            if mode == "warm":
                start_warm(small, work / "lake", env, home)
                runs = [warm_call(small, work / "lake", env, home)
                        for _ in range(args.repeat)]
                runs = [{k: r.get(k, float("nan")) for k in ("wall", "fixed", "stages",
                                                              *PARTS, *WARM_PARTS)}
                        for r in runs]
            else:
                runs = [real_call(small, work / "lake", env) for _ in range(args.repeat)]
                for r in runs:
                    r["outside the flows"] = (r["interpreter + exit"] + r["CLI imports"]
                                              + r["server wait"] + r["imports, params"]
                                              + r["tail"])
                    r["flows and tasks"] = r["flow runs"] + r["per task"] + r["between tasks"]
            rows[mode] = {k: statistics.median(r[k] for r in runs) for k in runs[0]}
            if mode in ("shared", "warm"):  # the anchor is plain Prefect: the same server
                state = json.loads((home / "prefect" / "shared-server.json").read_text())
                env = dict(env, PREFECT_API_URL=state["url"])
            rows[mode]["anchor"] = statistics.median(anchor(env) for _ in range(args.repeat))
            print(f"  {mode}: " + ", ".join(f"{k} {v:.2f}" for k, v in rows[mode].items()),
                  flush=True)
        ref = real_call(big, work / "lake-ref", _env(home, "shared", None))
    finally:
        if server is not None:
            server.stop()
        from v2xlake.flows.settings import configure_prefect

        configure_prefect()
        shared_server.stop()
        from v2xlake.flows import warm

        warm.stop(home / "prefect")
    print(f"a real call on a 1 s camera-less clip, medians of {args.repeat} fresh processes "
          f"(s); reference: a {args.reference_seconds:g} s camera-less clip's stages took "
          f"{ref['stages']:.1f} s (call {ref['wall']:.1f} s)", flush=True)
    print(f"  {'':28s}" + "".join(f"{m:>11s}" for m in modes))
    for key in ("wall", "stages", "fixed", *PARTS, *WARM_PARTS, "anchor"):
        print(f"  {key:28s}" + "".join(f"{rows[m][key]:11.2f}" for m in modes))
    for m in modes:
        f = rows[m]["fixed"]
        print(f"  {m}: fixed {f:.2f} s = {100 * f / ref['stages']:.1f} % of the "
              f"{args.reference_seconds:g} s clip's processing; fixed / 7-task anchor = "
              f"{f / rows[m]['anchor']:.2f}", flush=True)


if __name__ == "__main__":
    main()
