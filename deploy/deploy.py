"""Create every deployment of deploy/prefect.yaml on a running Prefect server, with the work
pools it names, or fail naming what is missing.

    export PREFECT_API_URL=http://127.0.0.1:<port>/api    # python deploy/start_server.py
    python deploy/deploy.py [--prefect-file deploy/prefect.yaml] [--no-create-pools]

Pools the file names and the server lacks are created (type process; existing pools, and
the concurrency limit deploy/start_cluster.py gives ``v2xlake-cluster``, are kept). Then
``prefect --no-prompt deploy --all`` runs from the repository root, and every deployment
the file declares is looked up on the server: exit 0 with the list, or exit 1 naming each
missing deployment and its pool (plain ``prefect deploy --all`` skips a deployment whose
pool is missing and still exits 0).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from v2xlake.flows.deployments import PREFECT_FILE, DeployError, deploy_all  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--api-url", default=os.environ.get("PREFECT_API_URL"),
                   help="the server's API (default: $PREFECT_API_URL)")
    p.add_argument("--prefect-file", type=Path, default=PREFECT_FILE)
    p.add_argument("--no-create-pools", action="store_true",
                   help="do not create missing work pools (their deployments then fail)")
    args = p.parse_args(argv)
    if not args.api_url:
        print("error: no Prefect API: set PREFECT_API_URL or pass --api-url "
              "(python deploy/start_server.py prints it)", file=sys.stderr)
        return 2
    try:
        res = deploy_all(args.api_url, args.prefect_file,
                         create_pools=not args.no_create_pools)
    except DeployError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    for pool in res.pools_created:
        print(f"work pool created: {pool}", flush=True)
    print(f"deployments: {', '.join(res.deployments)}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
