"""Does Dask earn its place: 4 camera clips, ``--runner dask`` (2 workers) against
``--runner local``, in the same run.

    python tests/bench/bench_dask.py [--work DIR] [--clips 4] [--seconds 1] [--order ld]
                                     [--stages] [--bound]

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
from an empty lake, so every stage runs in both. Each run's CPU is split into the CLI
process's own (flows, Prefect engine, Dask scheduler) and its children's (the Dask workers);
``--stages`` prints each stage's wall and CPU seconds.

``--bound`` adds what 2 cores allow at best: the local runner once more on one core with one
thread (affinity and the thread variables a Dask worker gets), and two single-threaded
CPU-bound processes against one (2.0 on two free cores). Two one-thread workers cannot beat
the one-core run's wall time divided by that scaling (clips split evenly, no start-up, no
per-task cost), so ``local wall x scaling / one-core wall`` bounds dask / local.
Not run by pytest.
"""

from __future__ import annotations

import argparse
import os
import re
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


def available_cores_list() -> list[int]:
    return sorted(os.sched_getaffinity(0))


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
        # per process of the tree: its own CPU (no children) the last time it was seen, and
        # its role: the CLI (flows, Prefect engine, Dask scheduler) or a child (Dask workers)
        self.own: dict[int, float] = {}
        self.role: dict[int, str] = {}
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
                self.own[p.pid] = t.user + t.system
                self.role.setdefault(p.pid, "cli" if p.pid == self.proc.pid else "children")
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
        by_role = {r: sum(c for p, c in self.own.items() if self.role[p] == r)
                   for r in ("cli", "children")}
        return {"cpu_cli": by_role["cli"], "cpu_children": by_role["children"],
                "busy_lt_0_5": sum(c < 0.5 for c in self.tree) / n,
                "busy_0_5_1_5": sum(0.5 <= c <= 1.5 for c in self.tree) / n,
                "busy_gt_1_5": sum(c > 1.5 for c in self.tree) / n,
                "tree_cores": sum(self.tree) / n, "machine_cores": sum(self.machine) / n}


def run(runner: str, clips: list[Path], lake: Path, env: dict[str, str],
        cores: list[int] | None = None) -> dict[str, Any]:
    """One ``v2xlake process`` run; ``cores``: the CPUs it may use (all when None)."""
    shutil.rmtree(lake, ignore_errors=True)
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", "v2xlake.flows.cli", "process",
                             *map(str, clips), "--lake", str(lake), "--runner", runner],
                            env=env, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True,
                            preexec_fn=(lambda: os.sched_setaffinity(0, cores)) if cores
                            else None)
    sampler = CoreSampler(proc.pid)
    stdout, stderr = proc.communicate()
    wall = time.perf_counter() - t0
    cores = sampler.close()
    res = subprocess.CompletedProcess(proc.args, proc.returncode, stdout, stderr)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if res.returncode != 0:
        raise RuntimeError(f"{runner} failed:\n{res.stdout[-3000:]}\n{res.stderr[-3000:]}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    stages = [ln for ln in res.stdout.splitlines() if " in " in ln and "/" in ln]
    # the stages' own CPU seconds (progress lines "... done in 2.0 s, cpu 1.8 s")
    stage_cpu = sum(float(m.group(1)) for ln in stages
                    if (m := re.search(r", cpu ([\d.]+) s", ln)))
    return {"wall": wall, "cpu": cpu, "clips_per_min": 60 * len(clips) / wall, **cores,
            "stage_cpu": stage_cpu, "stages": stages}


SPIN = """
import sys, time
import numpy as np
a = np.random.default_rng(0).random((160, 160))
t0 = time.perf_counter(); n = 0
while time.perf_counter() - t0 < float(sys.argv[1]):
    b = a
    for _ in range(20):
        b = np.tanh(b @ a * 0.01)
    sum(i * i for i in range(20000)); n += 1
print(n / (time.perf_counter() - t0))
"""


def machine_scaling(seconds: float = 8.0) -> float:
    """Throughput of two single-threaded CPU-bound processes (NumPy + pure Python) over
    one's: 2.0 on two free cores; less when other jobs take cores, or when the two vCPUs
    share a physical core."""
    env = _env(**{k: "1" for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS",
                                    "MKL_NUM_THREADS")})

    def spin(n: int) -> float:
        procs = [subprocess.Popen([sys.executable, "-c", SPIN, str(seconds)], env=env,
                                  stdout=subprocess.PIPE, text=True) for _ in range(n)]
        return sum(float(p.communicate()[0]) for p in procs)

    one = spin(1)
    return spin(2) / one


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "v2x-bench-dask")
    ap.add_argument("--clips", type=int, default=4)
    ap.add_argument("--seconds", type=float, default=1.0)
    ap.add_argument("--order", default="ld",
                    help="l = local, d = dask, in this order (ldld: two pairs)")
    ap.add_argument("--stages", action="store_true", help="print each run's stage lines")
    ap.add_argument("--bound", action="store_true",
                    help="also run local on one core with one thread (what one worker does) "
                         "and measure two-process scaling: the best Dask can do here")
    args = ap.parse_args()
    work = args.work.resolve()
    work.mkdir(parents=True, exist_ok=True)
    os.environ.setdefault("V2XLAKE_HOME", str(work / "home"))
    os.environ.setdefault("V2XLAKE_CHECKSUM_CACHE", str(work / "sums.sqlite"))
    from v2xlake.flows.runners import available_cores, thread_env, worker_threads
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
        out: dict[str, dict[str, float]] = {}  # the latest run of each
        runs: dict[str, list[dict[str, float]]] = {}  # every run (--order ldld: pairs)
        order = args.order + ("1" if args.bound else "")
        for key in order:
            runner = {"l": "local", "d": "dask", "1": "local"}[key]
            name = "1 core" if key == "1" else runner
            # one core, one thread, as a Dask worker runs (thread variables and affinity)
            one = key == "1"
            renv = dict(env, **thread_env(1)) if one else env
            out[name] = r = run(runner, clips, work / f"lake-{key}", renv,
                                cores=[available_cores_list()[0]] if one else None)
            runs.setdefault(name, []).append(r)
            print(f"  {name:6s} wall {r['wall']:7.1f} s  cpu {r['cpu']:7.1f} s  "
                  f"{r['clips_per_min']:5.2f} clips/min; busy cores: run {r['tree_cores']:.2f}"
                  f" (time at <0.5 / 0.5-1.5 / >1.5 cores: {r['busy_lt_0_5']:.0%} / "
                  f"{r['busy_0_5_1_5']:.0%} / {r['busy_gt_1_5']:.0%}), whole machine "
                  f"{r['machine_cores']:.2f}; cpu of the CLI process {r['cpu_cli']:.1f} s, "
                  f"of its children {r['cpu_children']:.1f} s", flush=True)
            if args.stages:
                print("\n".join(f"    {ln}" for ln in r["stages"]), flush=True)
    finally:
        server.stop()
    # the i-th dask run against the i-th local run (--order ldld interleaves them, so a
    # change of the shared machine's load hits both sides of a pair alike)
    pairs = zip(runs.get("local", []), runs.get("dask", []), strict=False)
    for i, (lo, da) in enumerate(pairs):
        print(f"  pair {i + 1}: throughput dask / local = "
              f"{da['clips_per_min'] / lo['clips_per_min']:.2f}x (target 1.6x); "
              f"cpu dask / local = {da['cpu'] / lo['cpu']:.2f}x; the stages' own cpu "
              f"{lo['stage_cpu']:.1f} s local, {da['stage_cpu']:.1f} s on the workers "
              f"(+{100 * (da['stage_cpu'] / lo['stage_cpu'] - 1):.0f} %): with no start-up, "
              f"orchestration or idle worker, dask would need {da['stage_cpu'] / cores:.1f} s "
              f"= {lo['wall'] * cores / da['stage_cpu']:.2f}x local", flush=True)
    if args.bound and "local" in out:
        scale = machine_scaling()
        w1, wl = out["1 core"]["wall"], out["local"]["wall"]
        print(f"  two single-threaded processes: {scale:.2f}x one (2.00 on two free cores)\n"
              f"  local on 1 core: {w1:.1f} s = {w1 / wl:.2f}x local on {cores}: the local "
              f"runner already gets {w1 / wl:.2f} cores' work done\n"
              f"  best case for 2 one-thread workers (clips split evenly, no start-up, no "
              f"per-task cost): {w1 / scale:.1f} s = {wl * scale / w1:.2f}x local",
              flush=True)


if __name__ == "__main__":
    main()
