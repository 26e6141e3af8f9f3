"""Fixed cost of a call: the no-op re-run against a trivial Prefect flow, in the same run.

    python tests/bench/bench_noop.py [--work DIR] [--clips 1000] [--repeat 3] [--snapshot]

A small simulated clip (preset small, 1 s) is processed through every stage once (kept in
``--work``); ``--clips`` replicas of it make a lake where every clip is current
(``bench_scale.build_lake``: files hard-linked, manifests recorded as the flow would).

Each figure is one fresh process, timed from its start to its exit (best and median of
``--repeat``), so imports and interpreter start count:

* ``anchor 1 task`` / ``anchor 7 tasks``: a trivial Prefect flow (tests/trivial_flow.py; the
  second has process-clip's shape, 7 tasks in a row) with Prefect's temporary server, then
  with ``PREFECT_API_URL`` naming a running server;
* ``v2xlake process CLIP`` on the processed clip (a no-op: answered by ``flows.noop``
  before Prefect), with and without ``PREFECT_API_URL``;
* ``flow no-op``: the same question asked the old way, ``process_clips`` (Prefect starts,
  every stage is a task that finds its manifest current);
* ``current_summaries`` over the ``--clips`` replicas: per clip, with nothing remembered
  (first call after a code change), with the facts cache warm (each clip checked against
  its manifests) and with the answers remembered by the call before;
* where a real call's fixed cost goes (``--only fixed``): interpreter start, ``import
  prefect``, importing the flow module with every stage (``flows.pipeline``), the 7-task
  anchor against a running server (imports + flow and task runs), and the temporary
  server's start (the anchor on it minus the anchor with ``PREFECT_API_URL``).

Prints the figures and their ratios to the anchor. Not run by pytest.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
sys.path[:0] = [str(REPO), str(HERE), str(REPO / "tests")]
# the code the measured processes run: the checkout, or with --snapshot a copy of it taken
# at the start, so that edits made in the checkout while the bench runs (a shared checkout)
# neither re-run stages nor invalidate remembered answers halfway through
CODE = REPO

import bench_scale  # noqa: E402

TEMPLATE = bench_scale.TEMPLATE_ID


def build_template(work: Path) -> Path:
    """The small clip, processed (bench_scale's template layout, a 1 s small clip)."""
    tdir = work / "template"
    lake = tdir / "lake"
    if (lake / "manifests" / TEMPLATE / "align.json").exists():
        return lake
    shutil.rmtree(tdir, ignore_errors=True)
    tdir.mkdir(parents=True)
    cli = [sys.executable, "-m", "v2xlake.flows.cli"]
    print("building the template clip (small, 1 s, every stage) ...", flush=True)
    subprocess.run([*cli, "simulate", str(tdir / "clip"), "--seconds", "1", "--seed", "7",
                    "--clip-id", TEMPLATE], check=True, env=_env(), cwd=CODE)
    subprocess.run([*cli, "process", str(tdir / "clip"), "--lake", str(lake)], check=True,
                   env=_env(), cwd=CODE)
    return lake


def _env(**extra: str) -> dict[str, str]:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(CODE), str(CODE / "tests")]))
    env.pop("PREFECT_API_URL", None)
    env.update(extra)
    return env


def timed(cmd: list[str], repeat: int, env: dict[str, str]) -> dict[str, float]:
    walls = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        res = subprocess.run(cmd, env=env, cwd=CODE, capture_output=True, text=True)
        walls.append(time.perf_counter() - t0)
        if res.returncode != 0:
            raise RuntimeError(f"{cmd} failed:\n{res.stdout[-2000:]}\n{res.stderr[-3000:]}")
    return {"best": min(walls), "median": statistics.median(walls)}


PER_CLIP = """
import sys, time
t0 = time.perf_counter()
from pathlib import Path
from v2xlake.flows.noop import current_summaries
dirs = sorted(str(p) for p in Path(sys.argv[2]).iterdir())
t1 = time.perf_counter()
res = current_summaries(dirs, sys.argv[1])
t2 = time.perf_counter()
# clips not current (None) cost the check too; they happen when the stages' code changed
# after the lake was built (another checkout's edits): reported, not hidden
print(sum(r is not None for r in res), len(dirs), t1 - t0, t2 - t1)
"""

FLOW_NOOP = """
import sys
from v2xlake.flows.settings import prefect_session
from v2xlake.flows.pipeline import process_clips
with prefect_session():
    r = process_clips([sys.argv[1]], sys.argv[2])
assert all(o["status"] == "cached" for o in r[0]["stages"]), r
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "v2x-bench-noop")
    ap.add_argument("--clips", type=int, default=1000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--only", default="calls,clips,fixed", help="calls, clips, fixed")
    ap.add_argument("--snapshot", action="store_true",
                    help="measure a copy of the code taken now (a checkout others edit)")
    args = ap.parse_args()
    work = args.work.resolve()
    work.mkdir(parents=True, exist_ok=True)
    if args.snapshot:
        global CODE
        CODE = work / "snapshot"
        shutil.rmtree(CODE, ignore_errors=True)
        shutil.copytree(REPO / "v2xlake", CODE / "v2xlake",
                        ignore=shutil.ignore_patterns("__pycache__"))
        (CODE / "tests").mkdir()
        shutil.copy2(REPO / "tests" / "trivial_flow.py", CODE / "tests")
    os.environ.setdefault("V2XLAKE_HOME", str(work / "home"))
    os.environ["V2XLAKE_NOOP_CACHE"] = str(work / "noop-facts.json")
    from v2xlake.flows.settings import configure_prefect

    configure_prefect()
    tlake = build_template(work)
    clip = tlake.parent / "clip"
    py = sys.executable
    anchor1 = [py, str(CODE / "tests" / "trivial_flow.py")]
    anchor7 = [py, "-c", "from trivial_flow import trivial_clip_flow; trivial_clip_flow()"]
    process = [py, "-m", "v2xlake.flows.cli", "process", str(clip), "--lake", str(tlake)]
    flow_noop = [py, "-c", FLOW_NOOP, str(clip), str(tlake)]
    rows: dict[str, dict[str, float]] = {}
    env = _env()
    if "calls" in args.only:
        measure_calls(work, args.repeat, env, anchor1, anchor7, process, flow_noop, rows)
    if "fixed" in args.only:
        measure_fixed(work, args.repeat, env, anchor7)
    if args.clips and "clips" in args.only:
        root, inbox = bench_scale.build_lake(work, tlake, args.clips)
        from v2xlake.flows.noop import answers_dir

        # cold: nothing remembered (the first call after a code change); checked: the facts
        # cache warm, every clip checked against its manifests; remembered: the answers of
        # the previous call, re-validated by the stat of what they read
        for variant in ("cold", "checked", "remembered"):
            if variant != "remembered":
                shutil.rmtree(answers_dir(), ignore_errors=True)
            if variant == "cold":
                Path(os.environ["V2XLAKE_NOOP_CACHE"]).unlink(missing_ok=True)
            out = subprocess.run([py, "-c", PER_CLIP, str(root), str(inbox)], env=env,
                                 capture_output=True, text=True, cwd=CODE)
            if out.returncode != 0:
                raise RuntimeError(out.stderr[-3000:])
            ok, n, imp, check = out.stdout.split()[-4:]
            print(f"  current_summaries over {n} clips ({ok} current), {variant}: "
                  f"{float(check):.2f} s ({1000 * float(check) / int(n):.2f} ms per clip; "
                  f"imports {float(imp):.2f} s)", flush=True)


def measure_fixed(work: Path, repeat: int, env: dict[str, str], anchor7: list[str]) -> None:
    """A real call's fixed cost, part by part, each a fresh process (medians)."""
    from v2xlake.flows.server import start_server

    py = sys.executable
    print(f"fixed cost of a real call, {repeat} fresh processes each (median wall s):",
          flush=True)
    parts = {"python -c pass": [py, "-c", "pass"],
             "import prefect": [py, "-c", "import prefect"],
             "import flows.pipeline (prefect + every stage)":
                 [py, "-c", "import v2xlake.flows.pipeline"],
             "import + 7-task anchor, temporary server": anchor7}
    med = {name: timed(cmd, repeat, env)["median"] for name, cmd in parts.items()}
    server = start_server(work / "server")
    try:
        med["import + 7-task anchor, PREFECT_API_URL"] = timed(
            anchor7, repeat, _env(PREFECT_API_URL=server.api_url))["median"]
    finally:
        server.stop()
    for name, v in med.items():
        print(f"  {name:48s} {v:6.2f}", flush=True)
    flow_runs = (med["import + 7-task anchor, PREFECT_API_URL"] - med["import prefect"])
    server_start = (med["import + 7-task anchor, temporary server"]
                    - med["import + 7-task anchor, PREFECT_API_URL"])
    stages = med["import flows.pipeline (prefect + every stage)"] - med["import prefect"]
    for name, v in (("prefect import", med["import prefect"] - med["python -c pass"]),
                    ("stage imports", stages), ("flow + 7 task runs", flow_runs),
                    ("temporary server start", server_start)):
        print(f"  {name:28s} {v:6.2f} s = {100 * v / 10:5.1f} % of a 10 s clip", flush=True)


def measure_calls(work: Path, repeat: int, env: dict[str, str], anchor1: list[str],
                  anchor7: list[str], process: list[str], flow_noop: list[str],
                  rows: dict[str, dict[str, float]]) -> None:
    """Per call: the anchors, the no-op CLI call and the flow's no-op, in fresh processes."""
    print(f"per call, {repeat} fresh processes each (wall s, best / median):", flush=True)
    # first a call that refills the facts cache if the stages' code changed since the last
    # run (the figures below are for the cache as every later call finds it)
    subprocess.run(process, env=env, cwd=CODE, capture_output=True)
    def measure(run_env: dict[str, str], server: str, no_url: str) -> None:
        for name, cmd in ((f"anchor 1 task, {server}", anchor1),
                          (f"anchor 7 tasks, {server}", anchor7),
                          (f"v2xlake process (no-op), {no_url}", process),
                          (f"flow no-op (process_clips), {server}", flow_noop)):
            try:
                rows[name] = timed(cmd, repeat, run_env)
            except RuntimeError:  # the flow's own no-op asserts every stage was cached
                print(f"  {name:48s} skipped: a stage re-ran (its code changed during the "
                      "bench)", flush=True)
                continue
            print(f"  {name:48s} {rows[name]['best']:6.2f} / {rows[name]['median']:6.2f}",
                  flush=True)

    measure(env, "temporary server", "no API URL")
    from v2xlake.flows.server import start_server

    server = start_server(work / "server")
    try:
        measure(_env(PREFECT_API_URL=server.api_url), "PREFECT_API_URL", "PREFECT_API_URL")
    finally:
        server.stop()
    for api in ("temporary server", "PREFECT_API_URL"):
        a = rows[f"anchor 7 tasks, {api}"]["median"]
        key = "no API URL" if api == "temporary server" else api
        n = rows[f"v2xlake process (no-op), {key}"]["median"]
        print(f"  ratio ({api}): v2xlake no-op / 7-task anchor = {n / a:.3f}", flush=True)
        f = rows.get(f"flow no-op (process_clips), {api}", {}).get("median")
        if f:
            print(f"  ratios ({api}): flow no-op / anchor = {f / a:.2f}; v2xlake no-op / "
                  f"flow no-op = {n / f:.3f}", flush=True)


if __name__ == "__main__":
    main()
