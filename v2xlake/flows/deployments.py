"""Create every deployment of ``deploy/prefect.yaml``, with the work pools it needs, or fail
naming what is missing.

WHY: ``prefect deploy --all`` skips a deployment whose work pool does not exist and still
exits 0 (#26: ``process-clips-cluster`` silently absent). So the pools the file names are
created first (type process; an existing pool is left as it is, with its concurrency limit),
then ``prefect deploy --all`` runs, then the server is asked for every deployment the file
declares: any that is not there is an error with its name and pool. Used by
``deploy/deploy.py`` and ``deploy/start_server.py --deploy``.
"""

from __future__ import annotations

import os
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

REPO = Path(__file__).resolve().parents[2]
PREFECT_FILE = REPO / "deploy" / "prefect.yaml"


class DeployError(RuntimeError):
    """Some deployment of the file is not on the server after ``prefect deploy``."""


@dataclass
class DeployResult:
    deployments: list[str]
    pools_created: list[str] = field(default_factory=list)
    output: str = ""


def declared(prefect_file: Path = PREFECT_FILE) -> list[dict[str, Any]]:
    """The deployments of a prefect.yaml (name, work pool, entrypoint, ...)."""
    spec = yaml.safe_load(Path(prefect_file).read_text()) or {}
    deps = spec.get("deployments") or []
    if not deps:
        raise DeployError(f"{prefect_file} declares no deployments")
    return list(deps)


def declared_pools(prefect_file: Path = PREFECT_FILE) -> list[str]:
    pools: list[str] = []
    for d in declared(prefect_file):
        name = ((d.get("work_pool") or {}).get("name"))
        if name and name not in pools:
            pools.append(name)
    return pools


def _env(api_url: str) -> dict[str, str]:
    from v2xlake.flows.settings import configure_prefect

    configure_prefect()
    return dict(os.environ, PREFECT_API_URL=api_url, DO_NOT_TRACK="1",
                PREFECT_SERVER_ANALYTICS_ENABLED="false")


def _prefect(args: list[str], api_url: str, cwd: Path = REPO,
             timeout: float = 600.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "prefect", *args], cwd=cwd, env=_env(api_url),
                          capture_output=True, text=True, timeout=timeout)


def _client(api_url: str) -> Any:
    from prefect.client.orchestration import get_client
    from prefect.settings import PREFECT_API_URL, temporary_settings

    class _Ctx:
        def __enter__(self) -> Any:
            self.settings = temporary_settings(updates={PREFECT_API_URL: api_url})
            self.settings.__enter__()
            self.client = get_client(sync_client=True)
            return self.client.__enter__()

        def __exit__(self, *exc: Any) -> None:
            self.client.__exit__(*exc)
            self.settings.__exit__(*exc)

    return _Ctx()


def existing_pools(api_url: str) -> set[str]:
    with _client(api_url) as client:
        return {p.name for p in client.read_work_pools()}


def ensure_pools(api_url: str, pools: list[str]) -> list[str]:
    """Create the missing ones (type process); returns those created."""
    have = existing_pools(api_url)
    created = []
    for pool in pools:
        if pool in have:
            continue
        out = _prefect(["work-pool", "create", pool, "--type", "process"], api_url, timeout=120)
        if out.returncode != 0:
            raise DeployError(f"cannot create work pool {pool!r}: "
                              f"{(out.stdout + out.stderr)[-1500:]}")
        created.append(pool)
    return created


def deployments_on_server(api_url: str) -> dict[str, str]:
    """{deployment name: work pool name} of every deployment the server holds."""
    with _client(api_url) as client:
        return {d.name: d.work_pool_name or "" for d in client.read_deployments()}


def missing(declared_deps: list[dict[str, Any]], on_server: dict[str, str]) -> list[str]:
    """What the file declares that the server does not have, as 'NAME (pool POOL)'."""
    out = []
    for d in declared_deps:
        pool = (d.get("work_pool") or {}).get("name")
        if d["name"] not in on_server:
            out.append(f"{d['name']} (work pool {pool!r})" if pool else d["name"])
        elif pool and on_server[d["name"]] != pool:
            out.append(f"{d['name']} (on pool {on_server[d['name']]!r}, declared {pool!r})")
    return out


def deploy_all(api_url: str, prefect_file: Path = PREFECT_FILE, *,
               create_pools: bool = True) -> DeployResult:
    """Pools, then ``prefect --no-prompt deploy --all`` from the repository root (the
    entrypoints are relative to it), then the check; raises DeployError naming what is
    missing."""
    prefect_file = Path(prefect_file).resolve()
    deps = declared(prefect_file)
    created = ensure_pools(api_url, declared_pools(prefect_file)) if create_pools else []
    out = _prefect(["--no-prompt", "deploy", "--prefect-file", str(prefect_file), "--all"],
                   api_url)
    text = out.stdout + out.stderr
    try:
        gone = missing(deps, deployments_on_server(api_url))
    except Exception as e:  # the server is gone too: say so, with prefect's own words
        raise DeployError(f"cannot list deployments at {api_url} ({e}); prefect deploy "
                          f"exited {out.returncode}:\n{text[-2000:]}") from e
    if gone or out.returncode != 0:
        raise DeployError(f"not deployed from {prefect_file.name}: "
                          f"{', '.join(gone) or 'none missing'} (prefect deploy exited "
                          f"{out.returncode}):\n{text[-2000:]}")
    return DeployResult([d["name"] for d in deps], created, text)
