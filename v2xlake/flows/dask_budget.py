"""The Dask worker plugin that holds a worker to its thread budget (``flows.runners``).

A module of its own because it imports ``distributed`` (the CLI imports ``flows.runners``
for every command); workers import it by name when the plugin is registered.
"""

from __future__ import annotations

from typing import Any

from distributed.diagnostics.plugin import WorkerPlugin

from v2xlake.flows.runners import apply_thread_budget


class ThreadBudget(WorkerPlugin):
    """On each worker: ``runners.apply_thread_budget(threads, its cores)``; ``cores`` maps
    worker names (a local cluster's are 0, 1, ...) to the cores to pin it to."""

    name = "v2xlake-thread-budget"

    def __init__(self, threads: int, cores: dict[str, list[int]] | None = None) -> None:
        self.threads = threads
        self.cores = cores or {}

    def setup(self, worker: Any) -> None:
        apply_thread_budget(self.threads, self.cores.get(str(worker.name)))
