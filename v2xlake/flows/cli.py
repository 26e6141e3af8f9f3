"""The ``v2xlake`` command line (README "Command line"), built with typer.

Each command is a thin function: check its arguments, configure Prefect, lazily import the
flow or stage module it needs (so ``v2xlake --help`` stays fast), call it, print with rich.
Exit status: 0 success, 1 the work found problems (quarantined clip, audit findings, release
mismatch), 2 a usage or input error. A user error (bad SQL, unknown clip, a lake that does
not exist, bad parameters, a non-empty output folder) is one line on stderr, never a Python
traceback; ``ClipError`` texts keep their ``[stage]`` tag.
"""

from __future__ import annotations

import json
import os
import sys
import time
from collections.abc import Sequence
from enum import StrEnum
from pathlib import Path
from typing import Annotated, Any

import typer
from typer.exceptions import TyperException

from v2xlake.flows.settings import DEFAULT_LAKE, configure_prefect, prefect_session, v2xlake_home
from v2xlake.schemas.registry import STAGE_PACKAGES

# the standard stages, from the one stage list (reading it imports no stage and no pydantic)
STAGES_HELP = ",".join(p.rpartition(".")[2] for p in STAGE_PACKAGES)

app = typer.Typer(
    name="v2xlake", no_args_is_help=True, add_completion=False, pretty_exceptions_enable=False,
    help="Multi-agent driving recordings -> Parquet lake + DuckDB catalog, processed per clip "
         "by Prefect flows.")
params_app = typer.Typer(no_args_is_help=True, help="pipeline parameters")
release_app = typer.Typer(no_args_is_help=True, help="immutable, checksummed selections of clips")
plot_app = typer.Typer(no_args_is_help=True, help="pictures of stage results")
catalog_app = typer.Typer(no_args_is_help=True, help="the DuckDB catalog of a lake")
app.add_typer(params_app, name="params")
app.add_typer(release_app, name="release")
app.add_typer(plot_app, name="plot")
app.add_typer(catalog_app, name="catalog")


class UserError(Exception):
    """A mistake in what the user asked for: one line on stderr, exit status 2."""


class Storage(StrEnum):
    sqlite3 = "sqlite3"
    mcap = "mcap"
    ros1 = "ros1"


class Preset(StrEnum):
    small = "small"
    street = "street"
    coop = "coop"
    cats = "cats"


class PoseFormat(StrEnum):
    inspva = "inspva"
    odometry = "odometry"
    navsat_imu = "navsat-imu"
    tf = "tf"


class BagVersion(StrEnum):
    ros1 = "ros1"
    ros2 = "ros2"


class Ros2Storage(StrEnum):
    sqlite3 = "sqlite3"
    mcap = "mcap"


class Format(StrEnum):
    table = "table"
    csv = "csv"
    json = "json"


class OutFormat(StrEnum):
    table = "table"
    json = "json"


class ExportFormat(StrEnum):
    nuscenes = "nuscenes"
    eth3d = "eth3d"
    rosbag = "rosbag"
    opencood = "opencood"
    bev = "bev"
    scene_transfer = "scene-transfer"


LakeOpt = Annotated[str, typer.Option(
    "--lake", envvar="V2XLAKE_LAKE", help="lake root: a directory or s3://bucket/prefix")]
ParamsOpt = Annotated[Path | None, typer.Option(
    "--params", metavar="FILE.yaml", help="pipeline parameters, one section per stage and "
                                          "export format (see `v2xlake params show`)")]


def _console(stderr: bool = False) -> Any:
    from rich.console import Console

    return Console(stderr=stderr, highlight=False, soft_wrap=True)


def _esc(value: object) -> str:
    """``value`` as literal text in rich markup: errors, paths and ids carry ``[stage]`` tags
    and brackets that rich would otherwise take for markup and drop."""
    from rich.markup import escape

    return escape(str(value))


def _csv(text: str | None) -> list[str] | None:
    if not text:
        return None
    return [t.strip() for t in text.split(",") if t.strip()]


def open_lake(uri: str) -> Any:
    """An existing lake (a mistyped --lake is an error, never a silent empty answer)."""
    from v2xlake.storage.lake import Lake

    lake = Lake(uri, create=False)
    if not lake.looks_like_lake():
        raise UserError(f"no lake at {uri}: it has none of landing/, raw/, clean/, manifests/ "
                        "(mistyped --lake? `v2xlake process` creates one)")
    return lake


def _version(value: bool) -> None:
    if value:
        from v2xlake import __version__

        typer.echo(f"v2xlake {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    verbose: Annotated[bool, typer.Option("-v", "--verbose",
                                          help="show Prefect's own log lines")] = False,
    version: Annotated[bool, typer.Option("--version", callback=_version, is_eager=True,
                                          help="print the version and exit")] = False,
) -> None:
    configure_prefect(quiet=not verbose)
    if verbose:
        os.environ.setdefault("PREFECT_LOGGING_LEVEL", "INFO")


# ---------------------------------------------------------------- simulate / demo
def sim_config(preset: str, seconds: float | None, storage: str | None, seed: int | None,
               agents: str | None, cameras: str | None, clip_id: str | None = None,
               pose_format: str | None = None, radar: bool | None = None) -> Any:
    from v2xlake.tasks.simulate import SimConfig

    return SimConfig.preset(preset, seconds=seconds, storage=storage, seed=seed, agents=agents,
                            cameras=cameras, clip_id=clip_id, pose_format=pose_format,
                            radar=radar)


@app.command()
def demo(
    out: Annotated[Path, typer.Option(help="where the clip and lake go")] = Path("./demo-lake"),
    seconds: float = 2.0, cameras: int = 2, seed: int = 7,
    storage: Storage = Storage.sqlite3,
) -> int:
    """Simulate a small clip, process it end to end, show results."""
    from v2xlake.flows.demo import run_demo

    return run_demo(out, seconds=seconds, cameras=cameras, seed=seed, storage=storage.value)


@app.command()
def simulate(
    out: Annotated[Path, typer.Argument(help="clip folder to write")],
    preset: Preset = Preset.small,
    seconds: float | None = None,
    storage: Storage | None = None,
    seed: int | None = None,
    agents: Annotated[str | None, typer.Option(help="comma list, e.g. red,black,rsu")] = None,
    cameras: Annotated[str | None, typer.Option(
        help="how many cameras (N) or a comma list of names")] = None,
    clip_id: str | None = None,
    pose_format: Annotated[PoseFormat | None, typer.Option(
        help="how the vehicles' poses are recorded: vendor InsPva, nav_msgs/Odometry in a "
             "UTM map, NavSatFix + Imu, or /tf")] = None,
    radar: Annotated[bool, typer.Option(help="a 20 Hz front 4D radar on each vehicle")] = False,
) -> int:
    """Write a simulated multi-agent clip folder."""
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise UserError(f"output folder {out} exists and is not empty: simulate writes a new "
                        "clip folder and never overwrites (pick a new or empty folder)")
    from v2xlake.tasks.simulate import simulate as run_simulate

    cfg = sim_config(preset.value, seconds, storage.value if storage else None, seed, agents,
                     cameras, clip_id, pose_format.value if pose_format else None, radar or None)
    t0 = time.perf_counter()
    path = run_simulate(out, cfg)
    _console().print(f"simulated clip [bold]{_esc(cfg.name)}[/] ({preset.value}, "
                     f"{cfg.seconds:g} s, {','.join(cfg.agents)}, {cfg.storage}) -> "
                     f"{_esc(path)} in {time.perf_counter() - t0:.1f} s")
    return 0


# ---------------------------------------------------------------- process
def _progress_bar(console: Any, live: bool) -> Any:
    """rich's bar with a spinner, the step, done / total and the elapsed time (off when not
    ``live``: then the callers print plain lines)."""
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        SpinnerColumn,
        TextColumn,
        TimeElapsedColumn,
    )

    return Progress(SpinnerColumn(), TextColumn("{task.description}"), BarColumn(),
                    MofNCompleteColumn(), TimeElapsedColumn(), console=console,
                    transient=False, disable=not live)


class StageProgress:
    """Progress of in-process clip flows, fed by ``flows.pipeline.PROGRESS_HOOK`` events: a
    live bar on a terminal; elsewhere (a pipe, a CI log) one plain line per finished stage,
    flushed at once, so a long run never looks hung."""

    def __init__(self, total: int, console: Any, live: bool | None = None) -> None:
        self.console = console
        self.live = console.is_terminal if live is None else live
        self.total = max(total, 1)
        self.done = 0
        self.t0 = time.perf_counter()
        self.progress = _progress_bar(console, self.live)
        self.task = self.progress.add_task("starting Prefect", total=self.total)

    def line(self, text: str) -> None:
        """One plain line (not a terminal), with the run's elapsed time."""
        if not self.live:
            self.console.print(f"[{time.perf_counter() - self.t0:6.1f} s] {_esc(text)}",
                               highlight=False, markup=True)
            self.console.file.flush()

    def __call__(self, event: dict[str, Any]) -> None:
        if event.get("event") == "stage_start":
            self.progress.update(self.task, description=f"{event['clip_id']}: {event['stage']}")
        elif event.get("event") == "stage_end":
            self.done += 1
            self.progress.advance(self.task)
            status = event.get("status")
            detail = event.get("reason") or ""
            if status == "failed":
                self.progress.console.print(
                    f"[red]{_esc(event['clip_id'])}: {event['stage']} failed[/] "
                    f"{_esc(event.get('error'))}")
            self.line(f"{self.done}/{self.total} {event['clip_id']}: {event['stage']} "
                      f"{status} in {float(event.get('seconds') or 0):.1f} s"
                      + (f", cpu {event['cpu_seconds']:.1f} s" if event.get("cpu_seconds")
                         else "")
                      + (f" ({detail})" if detail else ""))

    def __enter__(self) -> StageProgress:
        self.progress.start()
        self.line(f"starting Prefect for {self.total} stage run(s) ...")
        return self

    def __exit__(self, *exc: object) -> None:
        self.progress.update(self.task, description="done")
        self.progress.stop()


class StepProgress:
    """Progress of an export, fed by its steps (``tasks.export.common.report_step``: what,
    units done, units in all): a live bar per step on a terminal; elsewhere one plain line
    per step finished and one per ``every`` units (clips, images, scans, messages; every unit
    of a step of at most ``each_up_to``), flushed
    at once, so a long export never looks hung in a pipe or a CI log."""

    def __init__(self, console: Any, live: bool | None = None, every: int = 100,
                 each_up_to: int = 5) -> None:
        self.console = console
        self.live = console.is_terminal if live is None else live
        self.every = max(1, every)
        self.each_up_to = each_up_to
        self.t0 = time.perf_counter()
        self.progress = _progress_bar(console, self.live)
        self.tasks: dict[str, Any] = {}

    def __call__(self, what: str, done: int, total: int | None = None) -> None:
        if self.live:
            if what not in self.tasks:
                self.tasks[what] = self.progress.add_task(_esc(what), total=total)
            self.progress.update(self.tasks[what], completed=done, total=total)
            return
        finished = total is not None and done >= total
        few = total is not None and total <= self.each_up_to  # a few clips: a line each
        if finished or few or done % self.every == 0:
            self.console.print(f"[{time.perf_counter() - self.t0:6.1f} s] {_esc(what)} "
                               f"{done}" + (f"/{total}" if total is not None else "")
                               + (" done" if finished else ""), highlight=False)
            self.console.file.flush()

    def __enter__(self) -> StepProgress:
        self.progress.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.progress.stop()


def stage_table(summary: dict[str, Any]) -> Any:
    from rich.table import Table

    table = Table(title=f"clip {_esc(summary['clip_id'])}: {summary['status']}")
    for col in ("stage", "status", "time [s]", "key metrics"):
        table.add_column(col)
    colors = {"done": "green", "cached": "cyan", "not_applicable": "yellow", "failed": "red"}
    for o in summary["stages"]:
        metrics = (o.get("report") or {}).get("metrics") or {}
        shown = ", ".join(f"{k}={_num(v)}" for k, v in list(metrics.items())[:5])
        status = o["status"]
        reason = (o.get("report") or {}).get("reason") or o.get("error") or ""
        table.add_row(o["stage"], f"[{colors.get(status, 'white')}]{status}[/]",
                      f"{float(o.get('seconds', 0.0)):.1f}", _esc(shown or reason[:80]))
    return table


def _num(v: Any) -> str:
    return f"{v:.4g}" if isinstance(v, float) else str(v)


def run_process(clip_dirs: Sequence[str], lake: str, runner: str = "local",
                stages: list[str] | None = None, params: Any = None,
                pipeline: str | None = None, console: Any = None,
                show_progress: bool = True) -> list[dict[str, Any]]:
    """Process clips through Prefect with a progress display; returns the per-clip summaries.

    Clips whose chosen stages are all current are answered first, without Prefect
    (``flows.noop``: the flow's own manifest check); Prefect starts only for the others, and
    not at all when there are none. ``params``: a mapping (a ``--params`` file's YAML) or a
    ``PipelineParams``."""
    from v2xlake.flows.noop import current_summaries
    from v2xlake.flows.runners import parse_runner

    console = console or _console()
    parse_runner(runner)
    # a PipelineParams or a mapping; not isinstance(BaseModel): pydantic is not imported
    # when the answer is remembered (flows.noop)
    raw = params.model_dump(mode="json") if hasattr(params, "model_dump") else params
    answered = current_summaries(clip_dirs, lake, stages, raw, pipeline)
    todo = [d for d, a in zip(clip_dirs, answered, strict=True) if a is None]
    if len(todo) < len(clip_dirs):
        console.print(f"{len(clip_dirs) - len(todo)} clip(s) already current (every stage's "
                      "manifest matches): not run")
    if not todo:
        return [a for a in answered if a is not None]

    # without PREFECT_API_URL: the temporary server the previous calls shared (started now
    # if none answers, flows.shared_server), else Prefect's own per-process one; either
    # comes up while the stages import
    from v2xlake.flows import shared_server, warm

    warm.note_prefect_call()  # a CLI call run here starts a warm process when done
    old_url = os.environ.get("PREFECT_API_URL")
    wait_server = shared_server.attach() if shared_server.enabled() else None
    try:
        return _run_attached(clip_dirs, todo, answered, lake, runner, stages, raw, pipeline,
                             console, show_progress, wait_server)
    finally:  # an in-process caller (tests, the Python API) gets its environment back
        if old_url is None:
            os.environ.pop("PREFECT_API_URL", None)


def _run_attached(clip_dirs: Sequence[str], todo: list[str],
                  answered: list[dict[str, Any] | None], lake: str, runner: str,
                  stages: list[str] | None, raw: Any, pipeline: str | None, console: Any,
                  show_progress: bool, wait_server: Any) -> list[dict[str, Any]]:
    from v2xlake.flows.runners import needs_api_server

    if wait_server is None and not needs_api_server(runner):
        from v2xlake.flows.server import prestart_temporary_server

        wait_server = prestart_temporary_server()
    from v2xlake.flows import pipeline as pipeline_mod
    from v2xlake.flows.params import parse_params

    if wait_server is not None:
        wait_server()
    run_params = parse_params(raw)  # bad parameters: an error before any clip is touched
    chosen = pipeline_mod.select(pipeline_mod.resolve_pipeline(pipeline), stages)

    def go() -> list[dict[str, Any]]:
        with prefect_session():
            return list(pipeline_mod.process_clips(
                list(todo), lake, stages, run_params.model_dump(mode="json"), pipeline,
                runner))

    server_cm: Any = None
    if needs_api_server(runner):
        from v2xlake.flows.server import running_server

        console.print("starting a Prefect server for the Dask workers ...")
        server_cm = running_server(v2xlake_home() / "server")
    try:
        if server_cm is not None:
            server_cm.__enter__()
        if show_progress:
            # the clips' flows run in this process with either runner (with Dask only their
            # stages run on the workers), so their stage events reach the display
            with StageProgress(len(chosen) * len(todo), console) as prog:
                pipeline_mod.PROGRESS_HOOK = prog
                try:
                    ran = go()
                finally:
                    pipeline_mod.PROGRESS_HOOK = None
        else:
            with console.status(f"processing {len(todo)} clip(s) on {runner} ..."):
                ran = go()
    finally:
        if server_cm is not None:
            server_cm.__exit__(None, None, None)
    it = iter(ran)
    return [a if a is not None else next(it) for a in answered]


def process_json(results: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """``--format json``: per clip its status and, per stage, status, seconds and metrics."""
    return [{"clip_id": r["clip_id"], "clip_dir": r.get("clip_dir"), "status": r["status"],
             "error": r.get("error"), "quarantine_report": r.get("quarantine_report"),
             "stages": [{"stage": o["stage"], "status": o["status"],
                         "seconds": round(float(o.get("seconds") or 0.0), 3),
                         "reason": (o.get("report") or {}).get("reason"),
                         "metrics": (o.get("report") or {}).get("metrics") or {}}
                        for o in r.get("stages", [])]} for r in results]


@app.command()
def process(
    clip_dirs: Annotated[list[Path], typer.Argument(metavar="CLIP_DIR...",
                                                    help="clip folders (bags + clip.yaml)")],
    lake: LakeOpt = DEFAULT_LAKE,
    runner: Annotated[str, typer.Option(
        help="local | dask (LocalCluster, 2 workers) | dask=ADDRESS | dask=N")] = "local",
    stages: Annotated[str | None, typer.Option(help=f"comma subset of {STAGES_HELP}")] = None,
    params: ParamsOpt = None,
    pipeline: Annotated[str | None, typer.Option(hidden=True)] = None,  # module:STAGES
    fmt: Annotated[OutFormat, typer.Option(
        "--format", help="table (and progress) or json (one document on stdout, progress "
                         "on stderr)")] = OutFormat.table,
) -> int:
    """Run the stages on clip folders through Prefect (clips already current: answered
    from their manifests, without starting Prefect)."""
    missing = [str(d) for d in clip_dirs if not (d / "clip.yaml").is_file()]
    if missing:
        raise UserError(f"not a clip folder (no clip.yaml): {', '.join(missing)}")
    console = _console(stderr=fmt is OutFormat.json)
    t0 = time.perf_counter()
    if params is not None:  # flows.params imports the clip contract's models (0.3 s)
        from v2xlake.flows.params import load_params_data

        params_data = load_params_data(params)
    else:
        params_data = None
    results = run_process([str(d) for d in clip_dirs], lake, runner, _csv(stages),
                          params_data, pipeline, console)
    ok = sum(r["status"] == "ok" for r in results)
    if fmt is OutFormat.json:
        sys.stdout.write(json.dumps(process_json(results), indent=1, default=str) + "\n")
        return 0 if ok == len(results) else 1
    for r in results:
        console.print(stage_table(r))
        if r["status"] != "ok":
            console.print(f"[red]{_esc(r['clip_id'])}: {r['status']}[/] {_esc(r.get('error'))}"
                          + (f"\n  report: {_esc(r['quarantine_report'])}"
                             if r.get("quarantine_report") else ""))
    console.print(f"{ok}/{len(results)} clip(s) ok in {time.perf_counter() - t0:.1f} s; "
                  f"lake: {_esc(lake)}")
    return 0 if ok == len(results) else 1


@params_app.command("show")
def params_show(
    params: ParamsOpt = None,
    clip: Annotated[Path | None, typer.Option(metavar="CLIP_DIR",
                                              help="apply this clip's params: block")] = None,
    stage: Annotated[str | None, typer.Option(help="only this section")] = None,
) -> int:
    """Print the effective parameters as YAML: defaults, then --params, then the clip's."""

    from v2xlake.flows.noop import (
        FactsCache,
        _digest,
        cached_section,
        flows_code,
        load_code_memo,
        save_code_memo,
    )
    from v2xlake.flows.params import clip_params, load_params_data
    from v2xlake.flows.stage_names import STAGE_NAMES, registry_stage
    from v2xlake.storage.manifest import code_version

    # each section remembered per code version (flows.noop): the stage modules that define
    # the config models (seconds of imports) are imported only when one changed
    raw = load_params_data(params) or {}
    names = [*STAGE_NAMES, "export"]
    if stage:
        if stage not in names:
            raise UserError(f"unknown section {stage!r}; known: {', '.join(names)}")
        names = [stage]
    own = clip_params(clip) if clip is not None else None
    cache = FactsCache()
    load_code_memo(cache)
    text = []
    for n in names:
        code = code_version(n)
        values = cached_section(cache, n, code, raw, None if n == "export" else own,
                                lambda n=n: registry_stage(n))  # type: ignore[misc]
        # the text with every description, remembered the same way: describing a section
        # imports its config models
        key = "@".join((n, code, flows_code(), _digest(values)))
        described = cache.get("described", key)
        if described is None:
            from v2xlake.flows.params import describe_params

            described = describe_params({n: values})
            cache.put("described", key, described)
        text.append(described)
    save_code_memo(cache)
    cache.save()
    sys.stdout.write("".join(text))
    return 0


# ---------------------------------------------------------------- query
def _cell(value: Any) -> Any:
    """A table cell as literal text: values are data, never rich markup (``'[/x]'`` made
    rich raise MarkupError)."""
    from rich.text import Text

    return Text("" if value is None else _num(value))


def print_arrow(table: Any, fmt: str, console: Any, title: str | None = None,
                max_rows: int = 50, total_rows: int | None = None) -> None:
    """Print ``table`` (the first rows of an answer of ``total_rows``, when given)."""
    total = table.num_rows if total_rows is None else total_rows
    if fmt == "json":
        sys.stdout.write(json.dumps(table.to_pylist(), default=str, indent=2) + "\n")
    elif fmt == "csv":
        import csv

        w = csv.writer(sys.stdout)
        w.writerow(table.column_names)
        for row in table.to_pylist():
            w.writerow([row[c] for c in table.column_names])
    else:
        from rich.table import Table
        from rich.text import Text

        t = Table(title=Text(title) if title else None)
        for c in table.column_names:
            t.add_column(Text(c))
        for row in table.slice(0, max_rows).to_pylist():
            t.add_row(*[_cell(row[c]) for c in table.column_names])
        console.print(t)
    shown = min(table.num_rows, max_rows) if fmt == "table" else table.num_rows
    if total > shown:
        more = f"... {total - shown:,} more rows (--max-rows N prints more)"
        if fmt == "table":
            console.print(_esc(more))
        else:
            _console(stderr=True).print(_esc(more))


def _watchdog(seconds: float) -> Any:
    """Exit the process (status 2, one line) if the query still runs ``seconds`` after its
    statement timeout should have stopped it: a single call of a function DuckDB cannot
    interrupt (``repeat('a', 2000000000)``) would otherwise run on."""
    import threading

    def fire() -> None:
        _console(stderr=True).print(f"[red]error[/]: query stopped: still running "
                                    f"{seconds:g} s after its start (statement timeout "
                                    "not honoured by a long function call)")
        sys.stderr.flush()
        os._exit(2)

    timer = threading.Timer(seconds, fire)
    timer.daemon = True
    timer.start()
    return timer


@app.command()
def query(
    sql: Annotated[str, typer.Argument(help="one SELECT over the catalog's views")],
    lake: LakeOpt = DEFAULT_LAKE,
    format: Annotated[Format, typer.Option("--format")] = Format.table,
    max_rows: Annotated[int | None, typer.Option(
        "--max-rows", min=0, help="rows fetched and printed (the rest are counted); "
        "default 50 for table, 1,000,000 for csv/json")] = None,
) -> int:
    """SQL over the catalog (read-only; statement timeout V2XLAKE_QUERY_TIMEOUT_S, memory
    limit V2XLAKE_QUERY_MEMORY)."""
    from v2xlake.storage.catalog import QUERY_MAX_ROWS, WHERE_GRACE_S, Catalog, query_bounds

    timeout, _, cap = query_bounds()
    rows = max_rows if max_rows is not None else (
        50 if format is Format.table else cap or QUERY_MAX_ROWS)
    guard = _watchdog(timeout + WHERE_GRACE_S)
    try:
        with Catalog(open_lake(lake), read_only=True) as cat:
            head = cat.user_query_head(sql, rows, timeout_s=timeout)
    finally:
        guard.cancel()
    print_arrow(head.table, format.value, _console(), max_rows=rows, total_rows=head.total_rows)
    return 0


# ---------------------------------------------------------------- export / convert / plot / audit
@app.command()
def export(
    fmt: Annotated[ExportFormat, typer.Argument(metavar="FORMAT")],
    out: Annotated[Path, typer.Option(help="output folder (new or empty)")],
    lake: LakeOpt = DEFAULT_LAKE,
    clip: Annotated[list[str] | None, typer.Option(help="clip id (repeatable; default all)")]
    = None,
    params: ParamsOpt = None,
    storage: Annotated[Ros2Storage | None, typer.Option(
        help="rosbag only: sqlite3 or mcap (zstd chunks, /tf, markers: opens in Foxglove)")]
    = None,
    fmt_out: Annotated[OutFormat, typer.Option(
        "--format", help="table, or json (one document on stdout)")] = OutFormat.table,
) -> int:
    """Export clips to a dataset format."""
    from v2xlake.flows.bookkeeping import query as run_query
    from v2xlake.flows.params import load_params
    from v2xlake.flows.release import call_export

    the_lake = open_lake(lake)
    cfg = load_params(params).export.section(fmt.value)
    if storage is not None:
        if fmt != ExportFormat.rosbag:
            raise UserError("--storage applies to the rosbag export only")
        cfg = cfg.model_copy(update={"storage": storage.value})
    known = {r["clip_id"] for r in run_query(
        the_lake, "SELECT clip_id FROM clips WHERE status = 'ok'").to_pylist()}
    clip_ids = list(clip) if clip else sorted(known)
    unknown = [c for c in clip_ids if c not in known]
    if unknown:
        raise UserError(f"unknown clip(s) {unknown} in {lake}; known: {sorted(known)}")
    if not clip_ids:
        raise UserError(f"no processed clips in {lake}")
    if out.exists() and any(out.iterdir()):
        raise UserError(f"output folder {out} is not empty; exports never overwrite")
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    console = _console(stderr=fmt_out is OutFormat.json)
    console.print(f"{_esc(f'exporting {len(clip_ids)} clip(s) as {fmt.value} -> {out}')} ...")
    from v2xlake.tasks.export.common import export_progress

    with StepProgress(console) as prog, export_progress(prog):
        metrics = call_export(fmt.value, the_lake, clip_ids, out, config=cfg)
    seconds = time.perf_counter() - t0
    if fmt_out is OutFormat.json:
        sys.stdout.write(json.dumps({"format": fmt.value, "out": str(out), "clips": clip_ids,
                                     "seconds": round(seconds, 3), "metrics": metrics},
                                    indent=1, default=str) + "\n")
        return 0
    console.print(metric_table(f"{fmt.value}: {len(clip_ids)} clip(s) -> {out} in "
                               f"{seconds:.1f} s", metrics))
    return 0


def metric_table(title: str, metrics: dict[str, Any]) -> Any:
    """A result's metrics as a two-column table (not a raw dict)."""
    from rich.table import Table

    table = Table(title=_esc(title), title_justify="left")
    table.add_column("metric")
    table.add_column("value", justify="right")
    for k, v in metrics.items():
        table.add_row(_esc(k), _num(int(v)) if isinstance(v, float) and v.is_integer()
                      else _num(v))
    return table


def known_clip(lake: str, clip: str) -> Any:
    """The lake, after checking that ``clip`` is a well-formed id of a processed clip."""
    from v2xlake.storage.lake import checked_clip_id

    the_lake = open_lake(lake)
    try:
        checked_clip_id(the_lake, clip)
    except ValueError as e:
        raise UserError(str(e)) from e
    if not the_lake.exists(the_lake.table_dir("clean", "clips", clip)):
        raise UserError(f"unknown clip {clip!r} in {lake}")
    return the_lake


@app.command()
def view(
    clip: Annotated[str, typer.Argument(help="clip id")],
    out: Annotated[Path, typer.Option(help="output folder")] = Path("view"),
    lake: LakeOpt = DEFAULT_LAKE,
    png: Annotated[bool, typer.Option(help="bird's-eye picture + camera images")] = True,
    mcap: Annotated[bool, typer.Option(help="one MCAP with every agent, for Foxglove")] = True,
    sample: Annotated[int | None, typer.Option(help="cooperative sample (default: middle)")]
    = None,
) -> int:
    """Look at a clip: a PNG of one cooperative sample and an MCAP that Foxglove opens."""
    from v2xlake.tasks.export.common import export_progress
    from v2xlake.tasks.export.view import ViewConfig, view_clip

    the_lake = known_clip(lake, clip)
    with StepProgress(_console(stderr=True)) as prog, export_progress(prog):
        paths = view_clip(the_lake, clip, out, ViewConfig(png=png, mcap=mcap, sample=sample))
    for p in paths:
        _console().print(_esc(p))
    return 0


@app.command("convert-bag")
def convert_bag(
    src: Path, dst: Path,
    to: Annotated[BagVersion, typer.Option()],
    storage: Annotated[Ros2Storage, typer.Option(help="ROS 2 storage for --to ros2")]
    = Ros2Storage.sqlite3,
) -> int:
    """Convert a bag between ROS 1 and ROS 2."""
    from v2xlake.tasks.export import convert_bag as run_convert

    if dst.exists():
        raise UserError(f"{dst} exists; a bag is never overwritten")
    try:
        out = run_convert(src, dst, to.value, storage=storage.value)
    except Exception as e:
        if not type(e).__module__.startswith("rosbags"):
            raise
        raise UserError(_bag_error(src, e)) from e
    _console().print(f"{_esc(src)} -> {_esc(out)} ({to.value})")
    return 0


@plot_app.command("registration")
def plot_registration(
    clip: Annotated[str, typer.Option(help="clip id")],
    out: Annotated[Path, typer.Option(help="PNG to write")],
    lake: LakeOpt = DEFAULT_LAKE,
    frame: Annotated[int | None, typer.Option(help="default: the middle registered frame")]
    = None,
) -> int:
    """The clip's registration over time (GICP vs clip estimate vs INS, 1-sigma, each
    frame's decision; OUT) and the bird's-eye view of one frame before and after
    refinement (OUT with a ``_bev`` suffix)."""
    from v2xlake.tasks.register.stage import plot_registration as run_plot
    from v2xlake.tasks.register.stage import plot_registration_timeline

    if out.is_dir():
        raise UserError(f"--out {out} is a folder; give the PNG file to write")
    the_lake = known_clip(lake, clip)
    timeline = plot_registration_timeline(the_lake, clip, out)
    _console().print(f"registration of clip {clip} over time -> {_esc(timeline)}")
    out = out.with_name(f"{out.stem}_bev{out.suffix or '.png'}")
    if frame is None:
        frames = sorted(set(the_lake.read_table("clean", "registrations", clip_id=clip,
                                                columns=["frame_idx"]).column(0).to_pylist()))
        if not frames:
            raise UserError(f"clip {clip} has no registrations in {lake}")
        frame = frames[len(frames) // 2]
    path = run_plot(the_lake, clip, frame, out)
    _console().print(f"registration of clip {clip}, frame {frame} -> {_esc(path)}")
    return 0


@app.command()
def calibration(
    clip: Annotated[str, typer.Argument(help="clip id")],
    lake: LakeOpt = DEFAULT_LAKE,
    fmt: Annotated[Format, typer.Option("--format")] = Format.table,
    frames: Annotated[bool, typer.Option(
        "--frames", help="per frame pair: GICP vs clip estimate vs eq. 1a, the 1-sigma and "
        "the decision with its reason")] = False,
) -> int:
    """Published vs refined LiDAR extrinsics per agent and sensor: the clip solve's
    correction (LiDAR frame), its 1-sigma, which one deskew, alignment and exports use, and
    why a published one is kept; ``--frames`` lists every registered frame pair."""
    from v2xlake.tasks.reader import compare_calibration
    from v2xlake.tasks.register.calibration import format_calibration, format_frames
    from v2xlake.tasks.register.stage import frame_rows

    if frames:
        fr = frame_rows(known_clip(lake, clip), clip)
        if not fr:
            raise UserError(f"clip {clip} has no registrations in {lake}")
        if fmt is Format.json:
            sys.stdout.write(json.dumps(fr, indent=1) + "\n")
        else:
            _console().print(_esc(format_frames(fr)))
        return 0
    rows = compare_calibration(known_clip(lake, clip), clip)
    if not rows:
        raise UserError(f"clip {clip} has no LiDAR calibration in {lake}")
    if fmt is Format.table:
        _console().print(_esc(format_calibration(rows)))
        return 0
    out = [{"agent_id": r.agent_id, "sensor": r.sensor,
            "published_T_ego_sensor": r.published.tolist(),
            "refined_T_ego_sensor": None if r.refined is None else r.refined.tolist(),
            "correction_m": r.correction_m, "correction_deg": r.correction_deg,
            "std_m": r.std_m if r.refined is not None else None,
            "std_deg": r.std_deg if r.refined is not None else None,
            "refined_components": r.refined_components, "usable": r.usable,
            "used": r.effective, "reason": r.reason} for r in rows]
    if fmt is Format.json:
        sys.stdout.write(json.dumps(out, indent=1) + "\n")
    else:
        import csv

        w = csv.writer(sys.stdout)
        keys = [k for k in out[0] if not k.endswith("T_ego_sensor")]
        w.writerow(keys)
        w.writerows([[o[k] for k in keys] for o in out])
    return 0


@app.command()
def audit(
    lake: LakeOpt = DEFAULT_LAKE,
    release: Annotated[str | None, typer.Option(help="audit this release instead")] = None,
) -> int:
    """Check that nothing identifying leaves the raw zone."""
    from v2xlake.audit import AuditError
    from v2xlake.audit import audit as run_audit

    try:
        the_lake = open_lake(lake)
        report = (run_audit(the_lake, release=release) if release
                  else run_audit(the_lake, "clean"))
    except AuditError as e:
        raise UserError(str(e)) from e
    console = _console()
    for f in report.findings:
        console.print(f"[red]{f.kind}[/] {_esc(f.location)}: {_esc(f.detail)}")
    console.print(_esc(report.summary()))
    return 0 if report.ok else 1


# ---------------------------------------------------------------- release / catalog
@release_app.command("build")
def release_build(
    name: str,
    where: Annotated[str, typer.Option(help="a boolean expression over the clips view")],
    lake: LakeOpt = DEFAULT_LAKE,
    formats: Annotated[str, typer.Option(help="comma list: lake,nuscenes,opencood,...")]
    = "lake",
    seed: Annotated[int | None, typer.Option(
        help="split seed (default: the release's SplitConfig)")] = None,
    fractions: Annotated[str | None, typer.Option(
        help="train,val,test (default: the release's SplitConfig)")] = None,
) -> int:
    """Build release NAME from a predicate on clips."""
    from v2xlake.flows.release import build_release, check_fractions
    from v2xlake.tasks.release_split import SplitConfig

    default = SplitConfig()  # the splits' one default; not imported before the command runs
    try:
        parts = (default.fractions if fractions is None
                 else check_fractions([float(x) for x in fractions.split(",")]))
    except ValueError as e:
        raise UserError(f"--fractions: {e}") from e
    the_lake = open_lake(lake)
    t0 = time.perf_counter()
    console = _console()
    with console.status(f"building release {name} ({formats}) ..."):
        meta = build_release(lake, name, where, _csv(formats) or ["lake"],
                             default.seed if seed is None else seed, parts)
    console.print(f"release [bold]{name}[/]: {len(meta['clip_ids'])} clip(s), splits "
                  f"{_esc(meta['split_counts'])}, formats {_esc(meta['formats'])} in "
                  f"{time.perf_counter() - t0:.1f} s")
    console.print(f"notes: {_esc(the_lake.path('releases', name, 'RELEASE.md'))}")
    return 0


@release_app.command("verify")
def release_verify(name: str, lake: LakeOpt = DEFAULT_LAKE) -> int:
    """Recompute every checksum of release NAME."""
    from v2xlake.flows.release import verify_release

    open_lake(lake)
    res = verify_release(lake, name)
    console = _console()
    for p in res.problems:
        console.print(f"[red]FAIL[/] {_esc(p)}")
    if res.ok:
        console.print(f"release {name}: {res.checked} files OK")
        return 0
    console.print(f"release {name}: {len(res.problems)} problem(s)")
    return 1


@release_app.command("list")
def release_list(lake: LakeOpt = DEFAULT_LAKE) -> int:
    """List the releases of a lake."""
    from v2xlake.flows.release import list_releases

    open_lake(lake)
    for name in list_releases(lake):
        print(name)
    return 0


@catalog_app.command("refresh")
def catalog_refresh(lake: LakeOpt = DEFAULT_LAKE) -> int:
    """Rebuild catalog.duckdb from the lake's files."""
    from v2xlake.flows.bookkeeping import refresh_catalog

    the_lake = open_lake(lake)
    refresh_catalog(the_lake)
    _console().print(f"catalog refreshed: {_esc(the_lake.catalog_path)}")
    return 0


# ---------------------------------------------------------------- entry point
def main(argv: Sequence[str] | None = None) -> int:
    """Run the CLI; returns the exit status (0 ok, 1 problems found, 2 usage/input error).

    As the program's entry (``argv`` None) the call runs in the warm process when one of
    this code and environment answers (``flows/warm.py``: Prefect and the stages already
    imported), else here; a call here that ran Prefect starts one for the next calls."""
    if argv is None:
        from v2xlake.flows import warm

        args = sys.argv[1:]
        code = warm.call(args)
        if code is not None:
            return code
        try:
            return _main(args)
        finally:
            warm.start_if_wanted()
    return _main(list(argv))


def _main(argv: list[str]) -> int:
    err = _console(stderr=True)
    try:
        rv = app(args=argv, prog_name="v2xlake", standalone_mode=False)
    except typer.Exit as e:
        return int(e.exit_code or 0)
    except typer.Abort:
        return 130
    except TyperException as e:  # usage errors: unknown option, bad choice, ...
        show = getattr(e, "show", None)
        if callable(show):
            show(file=sys.stderr)
        else:
            err.print(f"[red]error[/]: {_esc(_short(e))}")
        return int(getattr(e, "exit_code", 2) or 0)
    except KeyboardInterrupt:
        return 130
    except ImportError as e:
        err.print(f"[red]unavailable[/]: {_esc(_short(e))}")
        return 2
    except Exception as e:
        if _is_user_error(e):
            err.print(f"[red]error[/]: {_esc(_short(e))}")
            return 2
        raise
    return int(rv or 0)


def _bag_error(src: Path, e: Exception) -> str:
    """rosbags' error about ``src`` with the message types it could not know: a bag without
    type definitions (ROS 2 bags written before Iron, or stripped) names none of them."""
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore

    text = f"cannot convert {src}: {_short(e)}"
    try:
        with Reader(src) as reader:
            store = get_typestore(Stores.ROS2_HUMBLE)
            unknown = sorted({c.msgtype for c in reader.connections
                              if c.msgtype not in store.types})
    except Exception:  # not a ROS 2 bag folder either: rosbags' own words
        return text
    if unknown:
        text += (f"; message type(s) not in the bag and not standard ROS 2: "
                 f"{', '.join(unknown)} (their .msg definitions are needed)")
    return text


def _short(e: BaseException) -> str:
    from v2xlake.schemas.errors import bounded

    return bounded(f"{type(e).__name__}: {e}" if not str(e) else str(e))


def _is_user_error(e: Exception) -> bool:
    """Bad input from the user (imported here, after the fact, to keep --help light)."""
    from v2xlake.schemas.errors import ClipError
    from v2xlake.storage.lake import LakeWriteError

    if isinstance(e, UserError | ClipError | ValueError | FileNotFoundError | FileExistsError
                  | PermissionError | LakeWriteError):  # full disk, read-only lake: one line
        return True  # ParamsError is a ValueError
    if "duckdb" in type(e).__module__:  # bad SQL: the parser's message, no trace
        return True
    from v2xlake.flows.release import ReleaseError

    return isinstance(e, ReleaseError)


if __name__ == "__main__":
    raise SystemExit(main())
