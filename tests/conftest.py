"""Shared, session-scoped services for the end-to-end tests (all opt-in, none autouse).

- ``prefect_server``: a real ``prefect server start`` on a free port (scheduler loop 2 s),
  its URL exported as ``PREFECT_API_URL`` for subprocesses / Dask workers and entered as a
  Prefect settings context (heartbeats off) for flows run in this process.
- ``s3_server``: a real SeaweedFS S3 endpoint (``weed mini``) on free 127.0.0.1 ports with
  one bucket; ``s3_env`` exports its endpoint and credentials for one test.

Servers start at most once per session (Prefect's takes 10-20 s on 2 cores) and are stopped
by process group at the end, whatever happened.

Also: the ``real_data`` marker (tests/fixtures/real.py: skip without the real recordings,
fail under ``V2XLAKE_REQUIRE_REAL_DATA=1``), and the test oracles that scripts/bootstrap.sh
installs beside the venv (requirements-oracles.lock) put on ``sys.path``.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from tests.fixtures.processes import stop_group

REPO = Path(__file__).resolve().parents[1]
TESTS = REPO / "tests"

# nuscenes-devkit & co. live outside the venv's site-packages (its numpy<2 pin would break
# the venv's pip check); appended, so nothing in them shadows a package of the venv
ORACLES = Path(sys.prefix) / "test-oracles"
if ORACLES.is_dir() and str(ORACLES) not in sys.path:
    sys.path.append(str(ORACLES))


def pytest_configure(config: pytest.Config) -> None:
    """Bag checksums remembered across processes go to a file of this run, not ~/.v2xlake;
    shared Prefect servers started by tests stop 30 s after their last user."""
    import shutil
    import tempfile

    if "V2XLAKE_CHECKSUM_CACHE" not in os.environ:
        sums = tempfile.mkdtemp(prefix="v2xlake-sums-")
        config.add_cleanup(lambda: shutil.rmtree(sums, ignore_errors=True))
        os.environ["V2XLAKE_CHECKSUM_CACHE"] = str(Path(sums) / "sums.sqlite")
    # a CLI test without PREFECT_API_URL starts the shared temporary server: let it stop
    # soon after the test instead of the 600 s a user's shell gets
    os.environ.setdefault("V2XLAKE_SERVER_IDLE_S", "30")
    # no warm process (flows/warm.py) under the suite: each CLI call runs as its own process
    # unless a test asks for one (tests/test_warm.py)
    os.environ.setdefault("V2XLAKE_WARM", "0")


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_setup(item: pytest.Item) -> None:
    """``@requires_real_data(...)``: skip (or, under V2XLAKE_REQUIRE_REAL_DATA=1, fail) before
    any fixture of the test runs, module-scoped ones included."""
    from tests.fixtures.real import MARKER, require_real_data

    marks = list(item.iter_markers(MARKER))
    if marks:
        require_real_data(*[str(a) for m in marks for a in m.args])


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _pythonpath() -> str:
    parts = [str(REPO), str(TESTS)]
    old = os.environ.get("PYTHONPATH")
    return os.pathsep.join([*parts, old] if old else parts)


@pytest.fixture(scope="session")
def v2x_home(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """A private V2XLAKE_HOME (Prefect home, local catalogs) for the session."""
    home = tmp_path_factory.mktemp("v2xhome")
    old = {k: os.environ.get(k) for k in ("V2XLAKE_HOME", "PYTHONPATH")}
    os.environ["V2XLAKE_HOME"] = str(home)
    os.environ["PYTHONPATH"] = _pythonpath()
    from v2xlake.flows.settings import configure_prefect

    configure_prefect()
    yield home
    for k, v in old.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v


@dataclass
class PrefectServerInfo:
    api_url: str
    home: Path
    log_path: Path


@pytest.fixture(scope="session")
def prefect_server(v2x_home: Path) -> Iterator[PrefectServerInfo]:
    from v2xlake.flows.server import start_server

    server = start_server(v2x_home / "server", scheduler_loop_seconds=2, timeout=150)
    old = os.environ.get("PREFECT_API_URL")
    os.environ["PREFECT_API_URL"] = server.api_url
    try:
        from prefect.settings import (
            PREFECT_API_URL,
            PREFECT_FLOWS_HEARTBEAT_FREQUENCY,
            temporary_settings,
        )

        with temporary_settings(updates={PREFECT_API_URL: server.api_url,
                                         PREFECT_FLOWS_HEARTBEAT_FREQUENCY: None}):
            yield PrefectServerInfo(server.api_url, server.home, server.log_path)
            from prefect.logging.handlers import APILogHandler

            try:  # send buffered run logs while the server still listens
                APILogHandler().flush()
            except Exception:
                pass
    finally:
        if old is None:
            os.environ.pop("PREFECT_API_URL", None)
        else:
            os.environ["PREFECT_API_URL"] = old
        server.stop()


@dataclass
class S3Info:
    endpoint: str
    bucket: str
    access_key: str
    secret_key: str

    def env(self) -> dict[str, str]:
        return {"AWS_ENDPOINT_URL": self.endpoint, "AWS_ACCESS_KEY_ID": self.access_key,
                "AWS_SECRET_ACCESS_KEY": self.secret_key, "AWS_REGION": "us-east-1",
                "AWS_EC2_METADATA_DISABLED": "true"}


WEED_PORTS = ("master.port", "master.port.grpc", "volume.port", "volume.port.grpc",
              "filer.port", "filer.port.grpc", "s3.port", "s3.port.grpc", "admin.port",
              "admin.port.grpc", "webdav.port", "s3.port.iceberg", "s3.port.lance")


@pytest.fixture(scope="session")
def s3_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[S3Info]:
    """SeaweedFS ``weed mini``: master, volume, filer and S3 gateway in one process."""
    weed = shutil.which("weed") or str(Path(sys.executable).with_name("weed"))
    data = tmp_path_factory.mktemp("seaweed")
    ports = {name: _free_port() for name in WEED_PORTS}
    info = S3Info(f"http://127.0.0.1:{ports['s3.port']}", "lake", "v2xlake", "v2xlake-secret")
    env = dict(os.environ, AWS_ACCESS_KEY_ID=info.access_key,
               AWS_SECRET_ACCESS_KEY=info.secret_key)
    log = open(data / "weed.log", "wb")
    proc = subprocess.Popen(
        [weed, "mini", f"-dir={data}", "-ip=127.0.0.1", "-ip.bind=127.0.0.1",
         "-master.telemetry=false", "-admin.ui=false", f"-bucket={info.bucket}",
         *[f"-{k}={v}" for k, v in ports.items()]],
        env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        import boto3

        client = boto3.client("s3", endpoint_url=info.endpoint, region_name="us-east-1",
                              aws_access_key_id=info.access_key,
                              aws_secret_access_key=info.secret_key)
        deadline = time.monotonic() + 300  # a cap for a loaded machine, not a deadline
        while True:
            try:
                client.put_object(Bucket=info.bucket, Key="probe/ready", Body=b"1")
                client.delete_object(Bucket=info.bucket, Key="probe/ready")
                break
            except Exception:
                if proc.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError("weed mini did not come up:\n"
                                       + (data / "weed.log").read_text()[-3000:]) from None
                time.sleep(0.3)
        yield info
    finally:
        stop_group(proc, grace_s=20.0)
        log.close()


@pytest.fixture
def s3_env(s3_server: S3Info, monkeypatch: pytest.MonkeyPatch) -> S3Info:
    for k, v in s3_server.env().items():
        monkeypatch.setenv(k, v)
    return s3_server
