"""The ``v2xlake`` command line (DESIGN.md "Command line").

Each sub-command is a thin function: parse, configure Prefect, lazily import the stage or
flow module it needs (so ``v2xlake --help`` stays fast and a missing stage only breaks the
command that needs it), call it, print with rich. Exit status: 0 success, 1 the work found
problems (quarantined clip, audit findings, release mismatch), 2 usage / unavailable.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from v2xlake.flows.settings import configure_prefect, default_lake, prefect_session, v2xlake_home

STAGES_HELP = "ingest,qa,anonymize,deskew,register,annotate,align"


def _console(stderr: bool = False) -> Any:
    from rich.console import Console

    return Console(stderr=stderr, highlight=False)


def _csv(text: str | None) -> list[str] | None:
    if not text:
        return None
    return [t.strip() for t in text.split(",") if t.strip()]


# ---------------------------------------------------------------- simulate
def sim_config(preset: str, seconds: float | None, storage: str | None, seed: int | None,
               agents: str | None, cameras: str | None, clip_id: str | None = None) -> Any:
    from v2xlake.tasks.simulate import SimConfig

    return SimConfig.preset(preset, seconds=seconds, storage=storage, seed=seed, agents=agents,
                            cameras=cameras, clip_id=clip_id)


def cmd_simulate(args: argparse.Namespace) -> int:
    from v2xlake.tasks.simulate import simulate

    cfg = sim_config(args.preset, args.seconds, args.storage, args.seed, args.agents,
                     args.cameras, args.clip_id)
    t0 = time.perf_counter()
    out = simulate(Path(args.out), cfg)
    _console().print(f"simulated clip [bold]{cfg.name}[/] ({args.preset}, "
                     f"{cfg.seconds:g} s, {','.join(cfg.agents)}, {cfg.storage}) -> {out} "
                     f"in {time.perf_counter() - t0:.1f} s")
    return 0


# ---------------------------------------------------------------- process
class StageProgress:
    """Rich progress bar fed by flows.process.PROGRESS_HOOK events (in-process runs)."""

    def __init__(self, total: int, console: Any) -> None:
        from rich.progress import (
            BarColumn,
            MofNCompleteColumn,
            Progress,
            SpinnerColumn,
            TextColumn,
            TimeElapsedColumn,
        )

        self.progress = Progress(SpinnerColumn(), TextColumn("{task.description}"), BarColumn(),
                                 MofNCompleteColumn(), TimeElapsedColumn(), console=console,
                                 transient=False)
        self.task = self.progress.add_task("starting Prefect", total=max(total, 1))

    def __call__(self, event: dict[str, Any]) -> None:
        if event.get("event") == "stage_start":
            self.progress.update(self.task, description=f"{event['clip_id']}: {event['stage']}")
        elif event.get("event") == "stage_end":
            self.progress.advance(self.task)
            if event.get("status") == "failed":
                self.progress.console.print(
                    f"[red]{event['clip_id']}: {event['stage']} failed[/] {event.get('error')}")

    def __enter__(self) -> StageProgress:
        self.progress.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.progress.update(self.task, description="done")
        self.progress.stop()


def stage_table(summary: dict[str, Any]) -> Any:
    from rich.table import Table

    table = Table(title=f"clip {summary['clip_id']}: {summary['status']}")
    for col in ("stage", "status", "time [s]", "key metrics"):
        table.add_column(col)
    colors = {"done": "green", "cached": "cyan", "not_applicable": "yellow", "failed": "red"}
    for o in summary["stages"]:
        metrics = (o.get("report") or {}).get("metrics") or {}
        shown = ", ".join(f"{k}={_num(v)}" for k, v in list(metrics.items())[:5])
        status = o["status"]
        reason = (o.get("report") or {}).get("reason") or o.get("error") or ""
        table.add_row(o["stage"], f"[{colors.get(status, 'white')}]{status}[/]",
                      f"{float(o.get('seconds', 0.0)):.1f}", shown or reason[:80])
    return table


def _num(v: Any) -> str:
    return f"{v:.4g}" if isinstance(v, float) else str(v)


def run_process(clip_dirs: Sequence[str], lake: str, runner: str = "local",
                stages: list[str] | None = None, params: Any = None,
                pipeline: str | None = None, console: Any = None,
                show_progress: bool = True) -> list[dict[str, Any]]:
    """Process clips through Prefect with a progress display; returns the per-clip summaries."""
    from v2xlake.flows import pipeline as pipeline_mod
    from v2xlake.flows.params import parse_params
    from v2xlake.flows.runners import needs_api_server, parse_runner

    console = console or _console()
    run_params = parse_params(params)  # bad parameters: an error before any clip is touched
    chosen = pipeline_mod.select(pipeline_mod.resolve_pipeline(pipeline), stages)
    parse_runner(runner)

    def go() -> list[dict[str, Any]]:
        with prefect_session():
            return list(pipeline_mod.process_clips(
                list(clip_dirs), lake, stages, run_params.model_dump(mode="json"), pipeline,
                runner))

    server_cm: Any = None
    if needs_api_server(runner):
        from v2xlake.flows.server import running_server

        console.print("starting a Prefect server for the Dask workers ...")
        server_cm = running_server(v2xlake_home() / "server")
    try:
        if server_cm is not None:
            server_cm.__enter__()
        if show_progress and parse_runner(runner).kind == "local":
            with StageProgress(len(chosen) * len(clip_dirs), console) as prog:
                pipeline_mod.PROGRESS_HOOK = prog
                try:
                    return go()
                finally:
                    pipeline_mod.PROGRESS_HOOK = None
        with console.status(f"processing {len(clip_dirs)} clip(s) on {runner} ..."):
            return go()
    finally:
        if server_cm is not None:
            server_cm.__exit__(None, None, None)


def cmd_process(args: argparse.Namespace) -> int:
    from v2xlake.flows.params import load_params

    console = _console()
    t0 = time.perf_counter()
    results = run_process(args.clip_dirs, args.lake, args.runner, _csv(args.stages),
                          load_params(args.params), args.pipeline, console)
    for r in results:
        console.print(stage_table(r))
        if r["status"] != "ok":
            console.print(f"[red]{r['clip_id']}: {r['status']}[/] {r.get('error')}"
                          + (f"\n  report: {r['quarantine_report']}"
                             if r.get("quarantine_report") else ""))
    ok = sum(r["status"] == "ok" for r in results)
    console.print(f"{ok}/{len(results)} clip(s) ok in {time.perf_counter() - t0:.1f} s; "
                  f"lake: {args.lake}")
    return 0 if ok == len(results) else 1


def cmd_params_show(args: argparse.Namespace) -> int:
    """The effective parameters: defaults, then ``--params``, then a clip's own block."""
    import yaml

    from v2xlake.flows.params import clip_params, load_params
    from v2xlake.flows.pipeline import STAGES

    run = load_params(args.params)
    data = run.model_dump(mode="json")
    if args.clip:
        own = clip_params(args.clip)
        for stage in STAGES:
            data[stage.name] = run.for_stage(stage, own).model_dump(mode="json")
    if args.stage:
        if args.stage not in data:
            raise ValueError(f"unknown section {args.stage!r}; known: {sorted(data)}")
        data = {args.stage: data[args.stage]}
    sys.stdout.write(yaml.safe_dump(data, sort_keys=False))
    return 0


# ---------------------------------------------------------------- query
def print_arrow(table: Any, fmt: str, console: Any, title: str | None = None,
                max_rows: int = 50) -> None:
    if fmt == "json":
        sys.stdout.write(json.dumps(table.to_pylist(), default=str, indent=2) + "\n")
        return
    if fmt == "csv":
        import csv

        w = csv.writer(sys.stdout)
        w.writerow(table.column_names)
        for row in table.to_pylist():
            w.writerow([row[c] for c in table.column_names])
        return
    from rich.table import Table

    t = Table(title=title)
    for c in table.column_names:
        t.add_column(c)
    for row in table.slice(0, max_rows).to_pylist():
        t.add_row(*[_num(row[c]) if row[c] is not None else "" for c in table.column_names])
    console.print(t)
    if table.num_rows > max_rows:
        console.print(f"... {table.num_rows - max_rows} more rows (use --format csv)")


def cmd_query(args: argparse.Namespace) -> int:
    from v2xlake.flows.bookkeeping import query
    from v2xlake.storage.lake import Lake

    print_arrow(query(Lake(args.lake), args.sql), args.format, _console())
    return 0


# ---------------------------------------------------------------- export / convert / plot / audit
def cmd_export(args: argparse.Namespace) -> int:
    from v2xlake.flows.bookkeeping import query
    from v2xlake.flows.params import load_params
    from v2xlake.flows.release import call_export
    from v2xlake.storage.lake import Lake

    lake = Lake(args.lake)
    params = load_params(args.params)
    clip_ids = args.clip or [r["clip_id"] for r in query(
        lake, "SELECT clip_id FROM clips WHERE status = 'ok' ORDER BY 1").to_pylist()]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    metrics = call_export(args.format, lake, clip_ids, out,
                          config=params.export.section(args.format))
    _console().print(f"{args.format}: {len(clip_ids)} clip(s) -> {out} in "
                     f"{time.perf_counter() - t0:.1f} s {metrics}")
    return 0


def cmd_convert_bag(args: argparse.Namespace) -> int:
    """ROS 1 <-> ROS 2 (tasks.export.convert_bag: rosbags' converter + type translation)."""
    from v2xlake.tasks.export import convert_bag

    dst = Path(args.dst)
    if dst.exists():
        raise ValueError(f"{dst} exists; a bag is never overwritten")
    out = convert_bag(Path(args.src), dst, args.to, storage=args.storage)
    _console().print(f"{args.src} -> {out} ({args.to})")
    return 0


def cmd_plot(args: argparse.Namespace) -> int:
    from v2xlake.storage.lake import Lake
    from v2xlake.tasks.register.stage import plot_registration

    lake = Lake(args.lake)
    frame = args.frame
    if frame is None:  # the middle registered frame
        frames = sorted(set(lake.read_table("clean", "registrations", clip_id=args.clip,
                                            columns=["frame_idx"]).column(0).to_pylist()))
        if not frames:
            raise ValueError(f"clip {args.clip} has no registrations in {lake.uri}")
        frame = frames[len(frames) // 2]
    out = plot_registration(lake, args.clip, frame, Path(args.out))
    _console().print(f"registration of clip {args.clip}, frame {frame} -> {out}")
    return 0


def cmd_audit(args: argparse.Namespace) -> int:
    from v2xlake.storage.lake import Lake
    from v2xlake.tasks.anonymize.audit import audit

    lake = Lake(args.lake)
    report = audit(lake, args.release or "clean")
    console = _console()
    for f in report.findings:
        console.print(f"[red]{f.kind}[/] {f.location}: {f.detail}")
    console.print(report.summary())
    return 0 if report.ok else 1


# ---------------------------------------------------------------- release
def cmd_release_build(args: argparse.Namespace) -> int:
    from v2xlake.flows.release import build_release

    t0 = time.perf_counter()
    fractions = tuple(float(x) for x in args.fractions.split(","))
    if len(fractions) != 3:
        raise SystemExit("--fractions needs three numbers: train,val,test")
    meta = build_release(args.lake, args.name, args.where, _csv(args.formats) or ["lake"],
                         args.seed, (fractions[0], fractions[1], fractions[2]))
    console = _console()
    console.print(f"release [bold]{args.name}[/]: {len(meta['clip_ids'])} clip(s), splits "
                  f"{meta['split_counts']}, formats {meta['formats']} in "
                  f"{time.perf_counter() - t0:.1f} s")
    from v2xlake.storage.lake import Lake

    console.print(f"notes: {Lake(args.lake).path('releases', args.name, 'RELEASE.md')}")
    return 0


def cmd_release_verify(args: argparse.Namespace) -> int:
    from v2xlake.flows.release import verify_release

    res = verify_release(args.lake, args.name)
    console = _console()
    for p in res.problems:
        console.print(f"[red]FAIL[/] {p}")
    if res.ok:
        console.print(f"release {args.name}: {res.checked} files OK")
        return 0
    console.print(f"release {args.name}: {len(res.problems)} problem(s)")
    return 1


def cmd_release_list(args: argparse.Namespace) -> int:
    from v2xlake.flows.release import list_releases

    for name in list_releases(args.lake):
        print(name)
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from v2xlake.flows.demo import run_demo

    return run_demo(Path(args.out), seconds=args.seconds, cameras=args.cameras,
                    seed=args.seed, storage=args.storage)


# ---------------------------------------------------------------- parser
def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="v2xlake",
        description="Multi-agent driving recordings -> Parquet lake + DuckDB catalog, "
                    "processed per clip by Prefect flows.")
    p.add_argument("-v", "--verbose", action="store_true", help="show Prefect's own log lines")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def lake_arg(sp: argparse.ArgumentParser) -> None:
        sp.add_argument("--lake", default=default_lake(),
                        help="lake root: directory or s3://bucket/prefix (default ./lake or "
                             "$V2XLAKE_LAKE)")

    d = sub.add_parser("demo", help="simulate a small clip, process it end to end, show results")
    d.add_argument("--out", default="./demo-lake", help="where the clip and lake go")
    d.add_argument("--seconds", type=float, default=2.0)
    d.add_argument("--cameras", type=int, default=2)
    d.add_argument("--seed", type=int, default=7)
    d.add_argument("--storage", default="sqlite3", choices=["sqlite3", "mcap", "ros1"])
    d.set_defaults(func=cmd_demo)

    s = sub.add_parser("simulate", help="write a simulated multi-agent clip folder")
    s.add_argument("out")
    s.add_argument("--preset", default="small", choices=["small", "cats"])
    s.add_argument("--seconds", type=float)
    s.add_argument("--storage", choices=["sqlite3", "mcap", "ros1"])
    s.add_argument("--seed", type=int)
    s.add_argument("--agents", help="comma list, e.g. red,black,rsu")
    s.add_argument("--cameras", help="how many cameras (N) or a comma list of names")
    s.add_argument("--clip-id")
    s.set_defaults(func=cmd_simulate)

    pr = sub.add_parser("process", help="run the stages on clip folders through Prefect")
    pr.add_argument("clip_dirs", nargs="+", metavar="CLIP_DIR")
    lake_arg(pr)
    pr.add_argument("--runner", default="local",
                    help="local | dask (LocalCluster, 2 workers) | dask=ADDRESS | dask=N")
    pr.add_argument("--stages", help=f"comma subset of {STAGES_HELP}")
    pr.add_argument("--params", metavar="FILE.yaml",
                    help="pipeline parameters, one section per stage (see `params show`)")
    pr.add_argument("--pipeline", help=argparse.SUPPRESS)  # module:STAGES (test doubles)
    pr.set_defaults(func=cmd_process)

    pa_ = sub.add_parser("params", help="pipeline parameters")
    ps = pa_.add_subparsers(dest="params_command", required=True, metavar="ACTION")
    psh = ps.add_parser("show", help="print the effective parameters as YAML")
    psh.add_argument("--params", metavar="FILE.yaml", help="a run's parameters file")
    psh.add_argument("--clip", metavar="CLIP_DIR", help="apply this clip's params: block")
    psh.add_argument("--stage", help="only this section")
    psh.set_defaults(func=cmd_params_show)

    q = sub.add_parser("query", help="SQL over the catalog")
    q.add_argument("sql")
    lake_arg(q)
    q.add_argument("--format", default="table", choices=["table", "csv", "json"])
    q.set_defaults(func=cmd_query)

    e = sub.add_parser("export", help="export clips to a dataset format")
    e.add_argument("format", choices=["nuscenes", "eth3d", "rosbag", "opencood", "bev",
                                      "scene-transfer"])
    lake_arg(e)
    e.add_argument("--clip", action="append", help="clip id (repeatable; default all)")
    e.add_argument("--out", required=True)
    e.add_argument("--params", metavar="FILE.yaml", help="parameters; its export: section")
    e.set_defaults(func=cmd_export)

    c = sub.add_parser("convert-bag", help="convert a bag between ROS 1 and ROS 2")
    c.add_argument("src")
    c.add_argument("dst")
    c.add_argument("--to", required=True, choices=["ros1", "ros2"])
    c.add_argument("--storage", default="sqlite3", choices=["sqlite3", "mcap"],
                   help="ROS 2 storage for --to ros2")
    c.set_defaults(func=cmd_convert_bag)

    pl = sub.add_parser("plot", help="pictures of stage results")
    pl.add_argument("what", choices=["registration"])
    lake_arg(pl)
    pl.add_argument("--clip", required=True)
    pl.add_argument("--frame", type=int, default=None)
    pl.add_argument("--out", required=True)
    pl.set_defaults(func=cmd_plot)

    a = sub.add_parser("audit", help="check that nothing identifying leaves the raw zone")
    lake_arg(a)
    a.add_argument("--release")
    a.set_defaults(func=cmd_audit)

    r = sub.add_parser("release", help="immutable, checksummed selections of clips")
    rs = r.add_subparsers(dest="release_command", required=True, metavar="ACTION")
    rb = rs.add_parser("build", help="build release NAME from a predicate on clips")
    rb.add_argument("name")
    rb.add_argument("--where", required=True, help="SQL predicate on the clips view")
    rb.add_argument("--formats", default="lake", help="comma list: lake,nuscenes,opencood,...")
    rb.add_argument("--seed", type=int, default=0)
    rb.add_argument("--fractions", default="0.7,0.15,0.15")
    lake_arg(rb)
    rb.set_defaults(func=cmd_release_build)
    rv = rs.add_parser("verify", help="recompute every checksum of release NAME")
    rv.add_argument("name")
    lake_arg(rv)
    rv.set_defaults(func=cmd_release_verify)
    rl = rs.add_parser("list", help="list releases")
    lake_arg(rl)
    rl.set_defaults(func=cmd_release_list)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    configure_prefect(quiet=not args.verbose)
    if args.verbose:
        os.environ.setdefault("PREFECT_LOGGING_LEVEL", "INFO")
    try:
        return int(args.func(args) or 0)
    except ImportError as exc:
        _console(stderr=True).print(f"[red]unavailable[/]: {exc}")
        return 2
    except KeyboardInterrupt:
        return 130
    except Exception as exc:
        from v2xlake.flows.release import ReleaseError
        from v2xlake.schemas.errors import ClipError

        if isinstance(exc, ReleaseError | ClipError | ValueError | FileNotFoundError):
            # ParamsError is a ValueError: bad parameters are a usage error
            _console(stderr=True).print(f"[red]error[/]: {exc}")
            return 2
        raise


if __name__ == "__main__":
    raise SystemExit(main())
