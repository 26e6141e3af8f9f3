"""#16, crash hygiene: kills at chosen points, dead runs' leftovers, full and read-only disks,
servers that outlive their parent. Every fault here is real: a SIGKILL (of a child process,
sent by itself at the named point), a kernel write failure (file size limit; ENOSPC on a
tmpfs and a read-only bind mount where the test may mount), a killed parent process."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pyarrow as pa
import pytest

from tests.fixtures.minibag import MiniClip, write_clip
from v2xlake.flows.release import build_release, list_releases, verify_release
from v2xlake.storage.lake import HOST_TAG, Lake, LakeWriteError, owner_state, run_tag

REPO = Path(__file__).resolve().parents[2]
ENV = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), str(REPO / "tests")])}
OWNS = [("clean", "table_a"), ("clean", "table_b")]


def child(code: str, *args: str) -> subprocess.CompletedProcess[str]:
    """Run a Python child process on ``code`` (dedented), ``args`` as sys.argv[1:]."""
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code), *args], env=ENV,
                          capture_output=True, text=True, timeout=120)


def spawn(code: str, *args: str) -> subprocess.Popen[str]:
    """The same, left running (its stdout a pipe)."""
    return subprocess.Popen([sys.executable, "-c", textwrap.dedent(code), *args], env=ENV,
                            stdout=subprocess.PIPE, text=True)


def killed(proc: subprocess.CompletedProcess[str]) -> bool:
    return proc.returncode == -signal.SIGKILL


def table(value: int) -> pa.Table:
    return pa.table({"v": pa.array([value] * 3, pa.int64())})


def values(lake: Lake, name: str, clip: str = "c") -> set[int]:
    return set(lake.read_table("clean", name, clip_id=clip).column("v").to_pylist())


def no_leftovers(lake: Lake) -> list[str]:
    """Hidden files, staging folders and release builds anywhere in the lake."""
    return [str(p) for p in Path(lake.base).rglob("*")
            if p.name.startswith(".") or "_staging" in p.parts]


# ------------------------------------------------------------------ owners
def test_owner_tags_tell_live_dead_and_foreign_runs_apart() -> None:
    assert owner_state(f"x-{run_tag()}-abc") == "live"
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait(60)
    assert owner_state(f"x-p{proc.pid}.{HOST_TAG}-abc") == "dead"
    other = "ffffff" if HOST_TAG != "ffffff" else "000000"
    assert owner_state(f"x-p{os.getpid()}.{other}-abc") == "foreign"
    assert owner_state("no-owner-here") == "unowned"


# ------------------------------------------------------------------ a stage's publish
STAGE_CHILD = """
import os, signal, sys
import pyarrow as pa
from v2xlake.storage.lake import Lake
lake, point = Lake(sys.argv[1]), sys.argv[2]
h = lake.for_stage("st", [("clean", "table_a"), ("clean", "table_b")], atomic_clip="c")
for name in ("table_a", "table_b"):
    h.write_table("clean", name, pa.table({"v": pa.array([2] * 3, pa.int64())}), clip_id="c")
if point == "before_publish":
    os.kill(os.getpid(), signal.SIGKILL)
real = Lake._move_tree
def move_then_die(self, *a):
    real(self, *a)
    os.kill(os.getpid(), signal.SIGKILL)  # after the first table is swapped in
Lake._move_tree = move_then_die
h.publish_stage()
"""


@pytest.mark.parametrize("point", ["before_publish", "mid_publish"])
def test_a_stage_killed_never_stays_half_published(tmp_path: Path, point: str) -> None:
    lake = Lake(tmp_path / "lake")
    for name in ("table_a", "table_b"):
        lake.write_table("clean", name, table(1), clip_id="c")  # the previous run's output
    proc = child(STAGE_CHILD, lake.base, point)
    assert killed(proc), proc.stderr
    staged = list(Path(lake.base, "_staging", "c").iterdir())
    assert len(staged) == 1 and owner_state(staged[0].name) == "dead"
    if point == "before_publish":  # nothing of the killed run is visible
        assert values(lake, "table_a") == values(lake, "table_b") == {1}
    else:  # the kill really landed between the two swaps
        assert {frozenset(values(lake, "table_a")), frozenset(values(lake, "table_b"))} == {
            frozenset({1}), frozenset({2})}
    # the next run of any stage on this clip sweeps first: finish (journal) or drop
    lake.for_stage("other", [("clean", "table_c")], atomic_clip="c").discard_stage()
    want = {1} if point == "before_publish" else {2}
    assert values(lake, "table_a") == values(lake, "table_b") == want
    assert no_leftovers(lake) == []


def test_the_sweep_keeps_a_live_runs_staging_and_foreign_hosts(tmp_path: Path) -> None:
    lake = Lake(tmp_path / "lake")
    live = spawn("""
        import sys, time
        import pyarrow as pa
        from v2xlake.storage.lake import Lake
        h = Lake(sys.argv[1]).for_stage("st", [("clean", "table_a")], atomic_clip="c")
        h.write_table("clean", "table_a", pa.table({"v": [1]}), clip_id="c")
        print("ready", flush=True)
        time.sleep(60)
    """, lake.base)
    try:
        assert live.stdout is not None and live.stdout.readline().strip() == "ready"
        other = "ffffff" if HOST_TAG != "ffffff" else "000000"
        foreign = Path(lake.base, "_staging", "c", f"st-p{os.getpid()}.{other}-0123")
        foreign.mkdir(parents=True)
        assert lake.sweep().runs == []  # both kept: one is alive, one cannot be told
        assert len(list(Path(lake.base, "_staging", "c").iterdir())) == 2
        live.kill()
        live.wait(10)
        swept = lake.sweep()
        assert len(swept.runs) == 1 and foreign.exists()
        old = time.time() - 7 * 86400
        os.utime(foreign, (old, old))
        assert lake.sweep(foreign_older_than_s=86400).runs == [str(foreign)]
        assert no_leftovers(lake) == []
    finally:
        live.kill()
        live.wait(10)


def test_a_dead_writers_temporary_file_is_swept_a_live_ones_kept(tmp_path: Path) -> None:
    lake = Lake(tmp_path / "lake")
    proc = child("""
        import os, signal, sys
        import pyarrow as pa
        from v2xlake.storage.lake import Lake
        t = pa.table({"v": pa.array(range(1000), pa.int64())})
        with Lake(sys.argv[1]).open_writer("raw", "t", t.schema, clip_id="c") as w:
            w.write(t)
            w._out.flush()
            os.kill(os.getpid(), signal.SIGKILL)  # between the bytes and the rename
    """, lake.base)
    assert killed(proc), proc.stderr
    part = Path(lake.table_dir("raw", "t", "c"))
    (dead,) = list(part.iterdir())
    assert dead.name.startswith(".part.parquet.tmp-p") and lake.list_files(lake.base) == []
    mine = part / f".other.parquet.tmp-{run_tag()}-0"  # a write in progress in this process
    mine.write_bytes(b"x")
    assert lake.sweep().files == [str(dead)]
    assert list(part.iterdir()) == [mine]


# ------------------------------------------------------------------ release builds
@pytest.fixture(scope="module")
def fake_lake(tmp_path_factory: pytest.TempPathFactory) -> Lake:
    import test_flows_fakestages as fakes

    from v2xlake.flows.bookkeeping import refresh_catalog

    tmp = tmp_path_factory.mktemp("release")
    lake = Lake(tmp / "lake")
    for i in range(3):
        rep = fakes.fake_ingest(lake, fakes.make_fake_clip(tmp / "in", f"c{i}"))
        fakes.fake_annotate(lake, rep.clip_id)
    refresh_catalog(lake)
    return lake


def test_a_release_build_killed_half_way_is_swept_by_the_next(fake_lake: Lake) -> None:
    proc = child("""
        import os, signal, sys
        from v2xlake.flows import release
        real, n = release.ReleaseWriter.write, [0]
        def write(self, rel, data):
            n[0] += 1
            if n[0] == 3:
                os.kill(os.getpid(), signal.SIGKILL)
            real(self, rel, data)
        release.ReleaseWriter.write = write
        release.build_release(sys.argv[1], "r-killed", "true")
    """, fake_lake.base)
    assert killed(proc), proc.stderr
    building = list(Path(fake_lake.path("releases")).glob(".r-killed.building-*"))
    assert len(building) == 1 and "r-killed" not in list_releases(fake_lake.uri)
    meta = build_release(fake_lake.uri, "r-killed", "true")
    assert meta["clip_ids"] == ["c0", "c1", "c2"] and verify_release(fake_lake.uri,
                                                                      "r-killed").ok
    assert not list(Path(fake_lake.path("releases")).glob(".*"))


def test_release_verify_sees_added_hidden_files(fake_lake: Lake) -> None:
    build_release(fake_lake.uri, "r-dot", "clip_id = 'c0'")
    root = Path(fake_lake.path("releases", "r-dot"))
    (root / ".hidden").write_text("x")
    (root / "lake" / ".sneaky").mkdir()
    (root / "lake" / ".sneaky" / "payload.bin").write_bytes(b"y")
    problems = verify_release(fake_lake.uri, "r-dot").problems
    assert any(".hidden" in p for p in problems)
    assert any(".sneaky/payload.bin" in p for p in problems)
    with pytest.raises(Exception, match="release name"):
        verify_release(fake_lake.uri, "../raw")


# ------------------------------------------------------------------ full and read-only disks
INGEST_CHILD = """
import resource, signal, sys
from v2xlake.storage.lake import Lake
from v2xlake.tasks.ingest import run_ingest
if len(sys.argv) > 3:  # a file size limit: the kernel fails writes past it (EFBIG)
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (int(sys.argv[3]), int(sys.argv[3])))
run_ingest(Lake(sys.argv[1]), sys.argv[2])
"""


@pytest.fixture(scope="module")
def small_clip(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_clip(tmp_path_factory.mktemp("clip") / "c1",
                      MiniClip(seconds=0.3, points=2000, cameras=(), clip_id="c1"))


def _may_mount() -> bool:
    if shutil.which("unshare") is None or os.geteuid() != 0:
        return False
    probe = subprocess.run(["unshare", "-m", "sh", "-c", "mount -t tmpfs -o size=64k tmpfs "
                            "/mnt && umount /mnt"], capture_output=True)
    return probe.returncode == 0


def test_a_write_the_disk_refuses_names_the_file_and_leaves_nothing(
        tmp_path: Path, small_clip: Path) -> None:
    lake = Lake(tmp_path / "lake")
    proc = child(INGEST_CHILD, lake.base, str(small_clip), "60000")
    assert proc.returncode == 1
    last = proc.stderr.strip().splitlines()[-1]
    assert "LakeWriteError" in last and "cannot write" in last and "in the lake" in last, last
    assert "file size limit" in last
    assert_nothing_half_written(lake, small_clip)


def assert_nothing_half_written(lake: Lake, clip: Path) -> None:
    """No table, blob, staging or temporary file; the landing zone (the delivery as
    delivered, kept for diagnosis) holds whole copies only."""
    files = [p for p in Path(lake.base).rglob("*") if p.is_file()]
    landing = Path(lake.path("landing", "c1"))
    for f in files:
        assert f.is_relative_to(landing) and not f.name.startswith("."), f
        if f.name != "delivery.json":
            assert f.read_bytes() == (clip / f.relative_to(landing)).read_bytes(), f


@pytest.mark.skipif(not _may_mount(), reason="needs root with mount rights (unshare -m)")
def test_a_full_disk_enospc(tmp_path: Path, small_clip: Path) -> None:
    """A real ENOSPC: the lake on a 256 KiB tmpfs in a private mount namespace (gone with it),
    so the listing of what is left is taken inside."""
    lake = tmp_path / "lake"
    lake.mkdir()
    copy = tmp_path / "after"
    script = (f"mount -t tmpfs -o size=256k tmpfs {lake} && "
              f"{sys.executable} -c '{INGEST_CHILD}' {lake} {small_clip}; "
              f"echo rc=$?; cp -a {lake} {copy}")
    out = subprocess.run(["unshare", "-m", "sh", "-c", script], env=ENV, capture_output=True,
                         text=True, timeout=120)
    assert "no space left on the device" in out.stderr, out.stderr[-2000:]
    assert out.stdout.strip().splitlines()[-1] == "rc=1", out.stdout
    assert_nothing_half_written(Lake(copy), small_clip)


def test_a_read_only_lake_answers_queries_and_refuses_writes_in_one_line(
        tmp_path: Path, small_clip: Path, fake_lake: Lake) -> None:
    src = Path(fake_lake.base)
    ro = tmp_path / "ro"
    shutil.copytree(src, ro, ignore=shutil.ignore_patterns("releases"))
    before = sorted(str(p) for p in ro.rglob("*"))
    cli = f"{sys.executable} -m v2xlake.flows.cli"
    cmds = [f"{cli} query 'SELECT count(*) AS n FROM clips' --lake {ro} --format csv",
            f"{cli} release build r --where true --lake {ro}",
            f"{cli} catalog refresh --lake {ro}",
            f"{sys.executable} -c '{INGEST_CHILD}' {ro} {small_clip}"]
    body = "; ".join(f"{c}; echo rc=$?" for c in cmds)
    if os.geteuid() == 0:
        if not _may_mount():
            pytest.skip("root without mount rights: permissions do not bind root")
        argv = ["unshare", "-m", "sh", "-c",
                f"mount --bind {ro} {ro} && mount -o remount,ro,bind {ro} {ro} && {body}"]
        reason = "read-only file system"
    else:
        for p in [ro, *ro.rglob("*")]:
            if p.is_dir():
                p.chmod(0o555)
        argv = ["sh", "-c", body]
        reason = "permission denied"
    try:
        out = subprocess.run(argv, env={**ENV, "COLUMNS": "400"}, capture_output=True,
                             text=True, timeout=300)
    finally:
        for p in [ro, *ro.rglob("*")]:
            if p.is_dir():
                p.chmod(0o755)
    rcs = [line for line in out.stdout.splitlines() if line.startswith("rc=")]
    assert rcs == ["rc=0", "rc=2", "rc=2", "rc=1"], (out.stdout, out.stderr[-3000:])
    assert "n\n3" in out.stdout  # the query still answers
    cli_errors = [line for line in out.stderr.splitlines() if line.startswith("error:")]
    assert len(cli_errors) == 2 and all(reason in e for e in cli_errors), out.stderr[-3000:]
    # the CLI commands print one line each; only the bare run_ingest call has a traceback,
    # ending in the same clear error
    head = out.stderr.split("Traceback")[0].strip().splitlines()
    assert head == cli_errors
    last = out.stderr.strip().splitlines()[-1]
    assert last.startswith("v2xlake.storage.lake.LakeWriteError: cannot write") and reason in last
    assert sorted(str(p) for p in ro.rglob("*")) == before  # nothing written, nothing left


def test_lake_write_error_is_an_os_error_with_its_errno(tmp_path: Path) -> None:
    import errno

    lake = Lake(tmp_path / "lake")
    err = lake.write_error(lake.path("raw", "x.parquet"), OSError(errno.ENOSPC, "full"))
    assert isinstance(err, LakeWriteError) and err.errno == errno.ENOSPC
    assert str(err).startswith("cannot write raw/x.parquet in the lake ")
    assert lake.write_error("x", OSError(errno.EIO, "flaky")) is None  # transient: retried


# ------------------------------------------------------------------ servers and their parents
def _gone(pid: int, within: float = 10.0) -> bool:
    deadline = time.monotonic() + within
    while time.monotonic() < deadline:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return True
        try:  # a zombie whose parent has not reaped it yet is gone too
            if Path(f"/proc/{pid}/stat").read_text().split()[2] == "Z":
                return True
        except OSError:
            return True
        time.sleep(0.1)
    return False


PARENT = """
import json, subprocess, sys, time
from v2xlake.flows.server import guarded
p = subprocess.Popen(guarded([sys.executable, "-c", "import time; time.sleep(120)"]))
time.sleep(0.5)
kids = open(f"/proc/{p.pid}/task/{p.pid}/children").read().split()
print(json.dumps({"guard": p.pid, "server": int(kids[0])}), flush=True)
time.sleep(120)
"""


@pytest.mark.parametrize("victim", ["parent", "guard"])
def test_a_guarded_server_dies_with_a_killed_parent(victim: str) -> None:
    parent = spawn(PARENT)
    try:
        assert parent.stdout is not None
        pids = json.loads(parent.stdout.readline())
        os.kill(parent.pid if victim == "parent" else pids["guard"], signal.SIGKILL)
        assert _gone(pids["server"]), f"the server outlived its {victim}"
    finally:
        parent.kill()
        parent.wait(10)


def test_prefects_temporary_server_is_started_guarded(monkeypatch: pytest.MonkeyPatch) -> None:
    from prefect.server.api.server import SubprocessASGIServer

    from v2xlake.flows.server import GUARD, guard_ephemeral_server

    started: list[list[str]] = []

    class FakePopen:
        def __init__(self, args: list[str], **kw: object) -> None:
            started.append(args)

    guard_ephemeral_server()
    monkeypatch.setattr(subprocess, "Popen", FakePopen)
    server = SubprocessASGIServer.__new__(SubprocessASGIServer)
    server.port = 1
    server._run_uvicorn_command()
    assert started[0][1] == str(GUARD) and started[0][2] == str(os.getpid())
    assert "uvicorn" in started[0] and "prefect.server.api.server:create_app" in started[0]


# ------------------------------------------------------------------ input errors
@pytest.mark.parametrize("nan_at,expect", [
    ((0,), "ok"),  # the first fix (the local origin) NaN: dropped, the clip is fine
    ((3, 10, 20), "qa"),  # dropped samples are gaps: QA names them
    (tuple(range(60)), "ingest"),  # no finite sample at all
])
def test_nan_ins_latitude_is_never_a_crash(tmp_path: Path, nan_at: tuple[int, ...],
                                          expect: str) -> None:
    from v2xlake.flows.pipeline import STAGES
    from v2xlake.schemas.errors import ClipError

    clip = write_clip(tmp_path / "c", MiniClip(seconds=0.3, points=200, cameras=(),
                                               clip_id="nan", ins_nan_latitude=nan_at))
    lake, target = Lake(tmp_path / "lake"), str(clip)
    failed = "ok"
    for stage in STAGES[:4]:  # ingest, qa, anonymize, deskew
        try:
            target = stage.run(lake, target, stage.config_model()).clip_id
        except ClipError as e:
            assert e.clip_id == "nan" and e.agent_id == "red" and e.topic == "/red/ins"
            failed = stage.name
            break
    assert failed == expect
