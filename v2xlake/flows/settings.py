"""Prefect environment for every v2xlake entry point (CLI, demo, deployments, tests).

WHY a module of its own: Prefect reads most settings from the environment when it is first
used, so the defaults below must be in ``os.environ`` before the first flow runs. Every
command calls :func:`configure_prefect` first; values the user already exported win.

- no telemetry (the server otherwise tries a network lookup that hangs offline),
- a generous start-up timeout for the temporary server (20 s was hit on 2 cores),
- ``PREFECT_HOME`` under ``~/.v2xlake/prefect`` (or ``$V2XLAKE_HOME/prefect``) so the
  temporary server's SQLite database never lands in the user's working directory,
- flow heartbeats off (each flow otherwise waits about 1 s on the heartbeat thread; the
  environment variable does not remove it, ``temporary_settings`` does, see NOTES.md),
- without ``PREFECT_API_URL`` the CLI shares one temporary server between calls
  (``flows/shared_server.py``, stopped when idle); Prefect's own per-process one (with
  ``V2XLAKE_SHARED_SERVER=0``) runs under ``flows/guard.py`` (``prefect_session``), so a
  SIGKILLed run does not leave it behind.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

DEFAULT_LAKE = "./lake"


def v2xlake_home() -> Path:
    """Per-user state (Prefect home, local catalogs of S3 lakes)."""
    return Path(os.environ.get("V2XLAKE_HOME", "~/.v2xlake")).expanduser()


def default_lake() -> str:
    return os.environ.get("V2XLAKE_LAKE", DEFAULT_LAKE)


def prefect_env_defaults() -> dict[str, str]:
    return {
        "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
        "DO_NOT_TRACK": "1",
        "PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS": "120",
        "PREFECT_HOME": str(v2xlake_home() / "prefect"),
        "PREFECT_UI_ENABLED": "false",
    }


def configure_prefect(*, quiet: bool = False) -> None:
    """Put v2xlake's Prefect defaults into the environment (user values win).

    ``quiet``: the CLI draws its own progress and summary, so Prefect's console lines are
    silenced (they still reach the API, where the run pages show them). Must run before
    ``prefect`` is first imported, which is when Prefect configures logging.
    """
    for key, value in prefect_env_defaults().items():
        os.environ.setdefault(key, value)
    if quiet:
        os.environ.setdefault("PREFECT_LOGGING_HANDLERS_CONSOLE_LEVEL", "CRITICAL")
    Path(os.environ["PREFECT_HOME"]).expanduser().mkdir(parents=True, exist_ok=True)


@contextmanager
def prefect_session() -> Iterator[None]:
    """Context for running flows in this process: heartbeats off (saves ~1 s per flow)."""
    configure_prefect()
    from prefect.settings import (
        PREFECT_API_URL,
        PREFECT_FLOWS_HEARTBEAT_FREQUENCY,
        temporary_settings,
    )

    # a URL exported after Prefect was imported (flows.shared_server.attach in a process
    # that had imported Prefect already, as tests do) is not in Prefect's settings yet
    url = os.environ.get("PREFECT_API_URL") or PREFECT_API_URL.value()
    if not url:  # Prefect will start its temporary server: guard it
        from v2xlake.flows.server import guard_ephemeral_server

        guard_ephemeral_server()

    with temporary_settings(updates={PREFECT_FLOWS_HEARTBEAT_FREQUENCY: None,
                                     PREFECT_API_URL: url or None}):
        yield
