"""``--runner local|dask[=ADDRESS]``: where the per-clip work runs.

``local`` runs clips one after another in this process. ``dask`` starts a
``dask.distributed.LocalCluster`` (2 single-threaded worker processes: stages are
NumPy/Open3D heavy and hold the GIL or their own thread pools) for the duration of the
flow; ``dask=tcp://host:8786`` connects to a running scheduler instead. The clips' flows
run in this process (a few at a time) and submit their work to the cluster: every stage
as a task, and a chunked stage (``Stage.chunked``) as one task per chunk, so one long clip
uses every worker. Every Dask worker reports to the Prefect API named by
``PREFECT_API_URL``; without one each worker would start its own temporary server, so the
CLI refuses ``dask`` without it (see NOTES.md).
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any


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
        cluster_kwargs={"n_workers": spec.n_workers, "threads_per_worker": 1,
                        "processes": True, "dashboard_address": None},
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
    with LocalCluster(n_workers=spec.n_workers, threads_per_worker=1, processes=True,
                      dashboard_address=None) as cluster:
        yield cluster.scheduler_address, spec.n_workers


def needs_api_server(text: str) -> bool:
    """Dask workers must share one Prefect API; the temporary server is per process."""
    return parse_runner(text).kind == "dask" and not os.environ.get("PREFECT_API_URL")
