"""``--runner local|dask[=ADDRESS]``: where the per-clip work runs.

``local`` runs clips one after another in this process. ``dask`` starts a
``dask.distributed.LocalCluster`` (2 single-threaded worker processes: stages are
NumPy/Open3D heavy and hold the GIL or their own thread pools) for the duration of the
flow; ``dask=tcp://host:8786`` connects to a running scheduler instead. The clips' flows
run in this process (a few at a time) and submit their work to the cluster: every stage
as a task, and a chunked stage (``Stage.chunked``) as one task per chunk, so one long clip
uses every worker. Every Dask worker reports to the Prefect API named by
``PREFECT_API_URL``; without one each worker would start its own temporary server, so
without a user's URL the CLI exports the shared temporary server's
(``flows/shared_server.py``), or with ``V2XLAKE_SHARED_SERVER=0`` starts a ``prefect server``
for the run (``needs_api_server``).

Thread budget (#26): a worker runs one task at a time, but the stages inside it size their
own pools from the machine (anonymize's detector pool and ingest's PNG pool take
``os.cpu_count()``, numba and OpenCV take every core, BLAS too unless told), so two workers
on two cores ran four to eight busy threads. Each worker therefore gets ``cores // workers``
threads (at least 1): ``NUMBA_NUM_THREADS``, OpenMP/BLAS/numexpr variables and
``V2XLAKE_WORKER_THREADS`` in its environment (set by the nanny before the worker process
starts, so before numba is imported), and at start-up (``flows.dask_budget.ThreadBudget``)
``os.cpu_count()`` answering that budget (what Python 3.13's ``PYTHON_CPU_COUNT`` does),
``cv2.setNumThreads`` and, on Linux for a local cluster, the worker pinned to its own cores.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

from v2xlake.tasks.cores import available_cores

THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
               "VECLIB_MAXIMUM_THREADS", "NUMEXPR_NUM_THREADS", "NUMBA_NUM_THREADS",
               "V2XLAKE_WORKER_THREADS")


def worker_threads(n_workers: int, cores: int | None = None) -> int:
    """Threads per worker so that ``n_workers`` workers do not oversubscribe the cores."""
    return max(1, (cores or available_cores()) // max(1, n_workers))


def thread_env(threads: int) -> dict[str, str]:
    """Environment of a worker process with a budget of ``threads`` threads."""
    return {k: str(threads) for k in THREAD_VARS}


def apply_thread_budget(threads: int, pin: list[int] | None = None) -> None:
    """In the current process: thread variables, ``os.cpu_count``, OpenCV, affinity."""
    os.environ.update(thread_env(threads))
    os.cpu_count = lambda: threads  # the stages' pool sizes (Python 3.13: PYTHON_CPU_COUNT)
    if pin:
        with contextlib.suppress(AttributeError, OSError):
            os.sched_setaffinity(0, pin)
    with contextlib.suppress(Exception):  # OpenCV sizes its pool from the machine
        import cv2

        cv2.setNumThreads(threads)


def local_cluster_kwargs(n_workers: int, cores: int | None = None) -> dict[str, Any]:
    """``LocalCluster`` arguments: single-threaded workers, each with its thread budget."""
    threads = worker_threads(n_workers, cores)
    return {"n_workers": n_workers, "threads_per_worker": 1, "processes": True,
            "dashboard_address": None, "env": thread_env(threads)}


def pinning(n_workers: int) -> dict[str, list[int]]:
    """Worker name -> its own cores (local clusters; none when there are fewer cores than
    workers: then they share, and only the thread budget applies)."""
    try:
        cores = sorted(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return {}
    per = len(cores) // max(1, n_workers)
    if per < 1:
        return {}
    return {str(k): cores[k * per:(k + 1) * per] for k in range(n_workers)}


def register_budget(client: Any, n_workers: int, *, pin: bool) -> None:
    """Apply the budget on the client's workers (now and on any that join later)."""
    from v2xlake.flows.dask_budget import ThreadBudget

    threads = max(1, worker_threads(n_workers))
    client.register_plugin(ThreadBudget(threads, pinning(n_workers) if pin else None))


@dataclass(frozen=True)
class RunnerSpec:
    kind: str  # "local" | "dask"
    address: str | None = None
    n_workers: int = 2


def parse_runner(text: str) -> RunnerSpec:
    kind, _, rest = (text or "local").partition("=")
    kind = kind.strip().lower()
    if kind == "local":
        if rest:
            raise ValueError("--runner local takes no address")
        return RunnerSpec("local")
    if kind == "dask":
        rest = rest.strip()
        if rest.isdigit():  # dask=4: a local cluster of 4 workers
            return RunnerSpec("dask", None, int(rest))
        return RunnerSpec("dask", rest or None)
    raise ValueError(f"unknown runner {text!r}: use local or dask[=ADDRESS]")


def make_task_runner(text: str) -> Any:
    """A Prefect task runner for the spec (DaskTaskRunner for dask)."""
    spec = parse_runner(text)
    if spec.kind == "local":
        from prefect.task_runners import ThreadPoolTaskRunner

        return ThreadPoolTaskRunner(max_workers=1)
    from prefect_dask import DaskTaskRunner

    if spec.address:
        return DaskTaskRunner(address=spec.address)
    return DaskTaskRunner(
        cluster_class="distributed.LocalCluster",
        cluster_kwargs=local_cluster_kwargs(spec.n_workers),
    )


@contextlib.contextmanager
def dask_cluster(spec: RunnerSpec) -> Iterator[tuple[str, int]]:
    """(scheduler address, worker threads) of the spec's cluster, a LocalCluster started
    for the duration when the spec names no address."""
    from distributed import Client, LocalCluster

    if spec.address:
        with Client(spec.address, timeout=30) as client:
            threads = sum(client.nthreads().values())
        yield spec.address, max(threads, 1)
        return
    with LocalCluster(**local_cluster_kwargs(spec.n_workers)) as cluster, \
            Client(cluster) as client:
        register_budget(client, spec.n_workers, pin=True)
        yield cluster.scheduler_address, spec.n_workers


def needs_api_server(text: str) -> bool:
    """Dask workers must share one Prefect API; the temporary server is per process."""
    return parse_runner(text).kind == "dask" and not os.environ.get("PREFECT_API_URL")
