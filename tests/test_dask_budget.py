"""Dask workers are held to cores // workers threads: two workers on two cores must not run
four to eight busy threads (numba, OpenCV, BLAS and the stages' own pools)."""

from __future__ import annotations

import os

from v2xlake.flows.runners import (
    RunnerSpec,
    dask_cluster,
    local_cluster_kwargs,
    pinning,
    thread_env,
    worker_threads,
)


def test_budget_arithmetic() -> None:
    assert worker_threads(2, 2) == 1 and worker_threads(2, 16) == 8
    assert worker_threads(4, 2) == 1 and worker_threads(0, 3) == 3
    env = thread_env(3)
    assert env["NUMBA_NUM_THREADS"] == "3" and env["OMP_NUM_THREADS"] == "3"
    kw = local_cluster_kwargs(2, cores=8)
    assert kw["threads_per_worker"] == 1 and kw["env"]["OPENBLAS_NUM_THREADS"] == "4"
    pins = pinning(2)
    if len(os.sched_getaffinity(0)) >= 2:
        assert set(pins) == {"0", "1"} and not set(pins["0"]) & set(pins["1"])


def _probe() -> dict[str, object]:
    import cv2
    import numba

    return {"cpu_count": os.cpu_count(), "numba": numba.config.NUMBA_NUM_THREADS,
            "omp": os.environ.get("OMP_NUM_THREADS"), "cv2": cv2.getNumThreads(),
            "cores": sorted(os.sched_getaffinity(0)), "pid": os.getpid()}


def test_local_cluster_workers_keep_their_budget() -> None:
    from distributed import Client

    cores = len(os.sched_getaffinity(0))
    expect = max(1, cores // 2)
    with dask_cluster(RunnerSpec("dask", None, 2)) as (address, threads), \
            Client(address) as client:
        assert threads == 2
        workers = list(client.scheduler_info()["workers"])
        got = [client.submit(_probe, workers=[w], pure=False).result() for w in workers]
    assert len({g["pid"] for g in got}) == 2
    for g in got:
        assert g["cpu_count"] == expect and g["numba"] == expect, g
        assert g["omp"] == str(expect) and g["cv2"] <= expect, g
    if cores >= 2:  # each worker on its own cores
        assert not set(got[0]["cores"]) & set(got[1]["cores"]), got
