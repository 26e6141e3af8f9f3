"""Does Dask earn its place: 4 camera clips, ``--runner dask`` (2 workers) against
``--runner local``, in the same run.

    python tests/bench/bench_dask.py [--work DIR] [--clips 4] [--seconds 1] [--order ld]

Four small simulated clips (preset small: two vehicles, LiDAR + cameras, ``--seconds`` long,
different seeds) are processed through every stage into a fresh lake, once with each
runner, each a fresh ``v2xlake process`` process against one running Prefect server
(``PREFECT_API_URL``: what a Dask run needs, and the same for both). Figures: wall time, CPU
time of the process tree (children's rusage), throughput in clips per minute, and the
throughput ratio dask / local; and, sampled every 0.5 s, how many cores the run's process
tree kept busy (the share of its wall time at < 0.5, 0.5-1.5 and > 1.5 cores) beside the
whole machine's busy cores, since other jobs on a shared machine take cores from both runs.
The bag checksum cache is shared (the first runner hashes
the bags; ingest is ~2 % of a clip), ``--order`` says which runs first. Both runs start
from an empty lake, so every stage runs in both.
Not run by pytest.
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
sys.path[:0] = [str(REPO)]


def _env(**extra: str) -> dict[str, str]:
    env = dict(os.environ, PYTHONPATH=str(REPO))
    env.update(extra)
    return env


def simulate(work: Path, n: int, seconds: float) -> list[Path]:
    clips = []
    for i in range(n):
        d = work / "clips" / f"dask_bench_{i}"
        if not (d / "clip.yaml").exists():
            shutil.rmtree(d, ignore_errors=True)
            subprocess.run([sys.executable, "-m", "v2xlake.flows.cli", "simulate", str(d),
                            "--seconds", str(seconds), "--seed", str(11 + i), "--clip-id",
                            f"dask_bench_{i}"], check=True, env=_env(), cwd=REPO,
                           capture_output=True)
        clips.append(d)
    return clips


class CoreSampler:
    """Busy cores of a process tree (the CLI and the Dask workers it starts) and of the
    whole machine, sampled every ``period`` seconds while the run lasts."""

    def __init__(self, pid: int, period: float = 0.5) -> None:
        import psutil

        self.proc = psutil.Process(pid)
        self.period = period
        self.tree: list[float] = []
        self.machine: list[float] = []
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._loop, daemon=True)
        self.thread.start()

    def _cpu(self) -> float:
        import psutil

        total = 0.0
        try:
            procs = [self.proc, *self.proc.children(recursive=True)]
        except psutil.Error:
            return 0.0
        for p in procs:
            try:
                t = p.cpu_times()
                total += t.user + t.system + t.children_user + t.children_system
            except psutil.Error:
                pass
        return total

    def _loop(self) -> None:
        import psutil

        last, last_t = self._cpu(), time.perf_counter()
        psutil.cpu_percent(None)
        # a child's CPU vanishes from the sum when it exits: negative steps are dropped
        while not self.stop.wait(self.period):
            now, now_t = self._cpu(), time.perf_counter()
            self.tree.append(max(0.0, now - last) / (now_t - last_t))
            self.machine.append(psutil.cpu_percent(None) / 100 * (psutil.cpu_count() or 1))
            last, last_t = now, now_t

    def close(self) -> dict[str, float]:
        self.stop.set()
        self.thread.join()
        n = max(1, len(self.tree))
        return {"busy_lt_0_5": sum(c < 0.5 for c in self.tree) / n,
                "busy_0_5_1_5": sum(0.5 <= c <= 1.5 for c in self.tree) / n,
                "busy_gt_1_5": sum(c > 1.5 for c in self.tree) / n,
                "tree_cores": sum(self.tree) / n, "machine_cores": sum(self.machine) / n}


def run(runner: str, clips: list[Path], lake: Path, env: dict[str, str]) -> dict[str, Any]:
    shutil.rmtree(lake, ignore_errors=True)
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "v2xlake.flows.cli", "process",
                             *map(str, clips), "--lake", str(lake), "--runner", runner],
                            env=env, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    sampler = CoreSampler(proc.pid)
    stdout, stderr = proc.communicate()
    wall = time.perf_counter() - t0
    cores = sampler.close()
    res = subprocess.CompletedProcess(proc.args, proc.returncode, stdout, stderr)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if res.returncode != 0:
        raise RuntimeError(f"{runner} failed:\n{res.stdout[-3000:]}\n{res.stderr[-3000:]}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {"wall": wall, "cpu": cpu, "clips_per_min": 60 * len(clips) / wall, **cores,
            "stages": [ln for ln in res.stdout.splitlines() if " in " in ln and "/" in ln]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "v2x-bench-dask")
    ap.add_argument("--clips", type=int, default=4)
    ap.add_argument("--seconds", type=float, default=1.0)
    ap.add_argument("--order", default="ld", help="l = local, d = dask, in this order")
    ap.add_argument("--stages", action="store_true", help="print each run's stage lines")
    args = ap.parse_args()
    work = args.work.resolve()
    work.mkdir(parents=True, exist_ok=True)
    os.environ.setdefault("V2XLAKE_HOME", str(work / "home"))
    os.environ.setdefault("V2XLAKE_CHECKSUM_CACHE", str(work / "sums.sqlite"))
    from v2xlake.flows.runners import available_cores, worker_threads
    from v2xlake.flows.server import start_server
    from v2xlake.flows.settings import configure_prefect

    configure_prefect()
    cores = available_cores()
    print(f"{args.clips} camera clips ({args.seconds:g} s, preset small), {cores} cores; "
          f"dask: 2 workers x {worker_threads(2, cores)} thread(s)", flush=True)
    clips = simulate(work, args.clips, args.seconds)
    server = start_server(work / "server")
    try:
        env = _env(PREFECT_API_URL=server.api_url)
        out: dict[str, dict[str, float]] = {}
        for key in args.order:
            runner = {"l": "local", "d": "dask"}[key]
            out[runner] = r = run(runner, clips, work / f"lake-{runner}", env)
            print(f"  {runner:6s} wall {r['wall']:7.1f} s  cpu {r['cpu']:7.1f} s  "
                  f"{r['clips_per_min']:5.2f} clips/min; busy cores: run {r['tree_cores']:.2f}"
                  f" (time at <0.5 / 0.5-1.5 / >1.5 cores: {r['busy_lt_0_5']:.0%} / "
                  f"{r['busy_0_5_1_5']:.0%} / {r['busy_gt_1_5']:.0%}), whole machine "
                  f"{r['machine_cores']:.2f}", flush=True)
            if args.stages:
                print("\n".join(f"    {ln}" for ln in r["stages"]), flush=True)
    finally:
        server.stop()
    if {"local", "dask"} <= set(out):
        lo, da = out["local"], out["dask"]
        print(f"  throughput dask / local = {da['clips_per_min'] / lo['clips_per_min']:.2f}x "
              f"(target 1.6x); cpu dask / local = {da['cpu'] / lo['cpu']:.2f}x", flush=True)


if __name__ == "__main__":
    main()
