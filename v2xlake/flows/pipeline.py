"""The pipeline: the stages in order, and the flows that run them per clip.

``STAGES`` imports every registered stage's :class:`~v2xlake.schemas.stage.Stage` object, so a
stage whose module fails to import fails the command before any clip is touched, and the
call chain from the flow into every stage is plain Python (``flow -> run_stage ->
stage.run``).

``process_clip`` runs the stages in order as Prefect tasks (retries for transient errors,
none for bad input), each with its effective parameters (``flows.params``: run parameters,
then the clip's own ``params:`` block) and a lake handle that may write only the stage's own
tables. A stage is skipped when its ``storage.manifest`` key (checksums of the files it
reads, parameters, code) matches its last run. A stage that does not apply to the clip (no
pose, one agent) reports ``not_applicable`` with the reason; nothing is quarantined for it.
On :class:`~v2xlake.schemas.errors.ClipError` the clip is quarantined here, once, and the
flow run ends Failed with the reason. Artifacts: a stage table, per-stage metrics, the QA
checks and links to pictures.

``process_clips`` runs one ``process_clip`` flow per clip: one after another with the local
runner, or each inside a task on a Dask cluster (``--runner dask[=ADDRESS]``), so that every
clip has its own flow run and state, and one bad clip never stops the others.
"""

from __future__ import annotations

import contextvars
import re
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any
from uuid import UUID

from prefect import flow, get_run_logger, task
from prefect.artifacts import (
    create_markdown_artifact,
    create_progress_artifact,
    create_table_artifact,
    update_progress_artifact,
)
from pydantic import BaseModel

from v2xlake.flows import bookkeeping
from v2xlake.flows.params import ParamsError, clip_params, parse_params
from v2xlake.flows.stage_names import (  # re-exported: they lived here before
    UNREADABLE,
    peek_clip_id,
    resolve_pipeline,
    select,
)
from v2xlake.schemas.errors import ClipError, DeliveryConflict, error_text
from v2xlake.schemas.stage import Stage, StageReport
from v2xlake.storage.lake import CLIP_ID, ClipBusy, Lake, LakeWriteError
from v2xlake.storage.quarantine import REJECTED

# every registered stage (schemas/registry.py), imported now: one that fails to import fails
# the command before any clip is touched
STAGES: tuple[Stage[Any], ...] = resolve_pipeline()
STAGE_NAMES = tuple(s.name for s in STAGES)


# The CLI sets this to drive its progress display (only for in-process runs).
ProgressHook = Callable[[dict[str, Any]], None]
PROGRESS_HOOK: ProgressHook | None = None
# the UI's progress artifact of a clip is updated at most this often (and after its last stage)
PROGRESS_ARTIFACT_EVERY_S = 2.0


def _emit(**event: Any) -> None:
    hook = PROGRESS_HOOK
    if hook is not None:
        try:
            hook(event)
        except Exception:  # a display problem must never fail a clip
            pass


class ClipFailed(Exception):
    """A clip's flow failed; carries the per-stage summary so the caller can report it."""

    def __init__(self, message: str, summary: dict[str, Any]) -> None:
        super().__init__(message, summary)

    def __str__(self) -> str:
        return str(self.args[0])

    @property
    def summary(self) -> dict[str, Any]:
        return dict(self.args[1])


def _artifact_key(*parts: str) -> str:
    return re.sub(r"[^a-z0-9-]+", "-", "-".join(parts).lower()).strip("-")[:100]


#: Failures that a retry reproduces exactly: bad input, a lake that cannot take the write
#: (disk full, permissions) and programming errors. Retrying them only triples the time to
#: the error; what is left (network, timeouts, a lost worker) is worth another try.
DETERMINISTIC: tuple[type[BaseException], ...] = (
    ClipError, LakeWriteError, ClipBusy, ValueError, TypeError, KeyError, IndexError,
    AttributeError, ArithmeticError, AssertionError, NotImplementedError, MemoryError)


def _no_retry_on_bad_input(task: Any, task_run: Any, state: Any) -> bool:
    """Retry transient failures only: bad input stays bad, and so does a bug."""
    try:
        state.result()
    except DETERMINISTIC:
        return False
    except Exception:
        return True
    return False


def _execute(stage: Stage[Any], lake_uri: str, target: str, clip_id: str, cfg: BaseModel,
             do: Callable[[Lake, str, BaseModel], StageReport]) -> dict[str, Any]:
    """Run one stage on one clip unless its manifest says it is current: key, staged
    output published together, paths recorded as final, manifest written."""
    lake = Lake(lake_uri)
    # one run at a time per clip, from deciding what to run to the manifest (#25)
    with lake.clip_lock(clip_id):
        return _execute_locked(lake, stage, target, clip_id, cfg, do)


def _execute_locked(lake: Lake, stage: Stage[Any], target: str, clip_id: str,
                    cfg: BaseModel, do: Callable[[Lake, str, BaseModel], StageReport]
                    ) -> dict[str, Any]:
    logger = get_run_logger()
    clip_dir = Path(target) if stage.input == "clip_dir" else None
    key = bookkeeping.stage_key(lake, clip_id, stage, cfg, clip_dir)
    cached = bookkeeping.cached_report(lake, clip_id, stage.name, key)
    if cached is not None:
        logger.info("%s: %s unchanged since its last run, skipped", clip_id, stage.name)
        return {"stage": stage.name, "status": "cached", "seconds": 0.0,
                "report": cached.model_dump(mode="json")}
    t0, c0 = time.perf_counter(), time.process_time()
    # the handle refuses reads of tables the stage did not declare (they would be missing
    # from its manifest key, so a change to them would not re-run it)
    writer = lake.for_stage(stage.name, [(t.zone, t.name) for t in stage.owns],
                            atomic_clip=clip_id if stage.atomic else None,
                            reads=[(t.zone, t.name) for t in stage.reads])
    try:
        report = do(writer, str(clip_dir) if clip_dir is not None else target, cfg)
        if not isinstance(report, StageReport):
            report = StageReport.model_validate(report)
        moved = writer.publish_stage()  # the stage's tables become visible together
    except BaseException:
        writer.discard_stage()
        raise
    for out in report.outputs:  # recorded paths: staged -> final (absolute or lake-relative)
        for src, dst in moved.items():
            for a, b in ((src, dst), (src[len(lake.base) + 1:], dst[len(lake.base) + 1:])):
                if out.path.startswith(a + "/"):
                    out.path = b + out.path[len(a):]
    seconds = time.perf_counter() - t0
    # the CPU of the process running it (on a Dask worker: this stage's own; locally the
    # flow's threads too): where a distributed run's extra CPU goes (#26)
    cpu = time.process_time() - c0
    if report.clip_id != clip_id:
        key = bookkeeping.stage_key(lake, report.clip_id, stage, cfg, clip_dir)
    bookkeeping.record(lake, report, key)
    if report.status == "not_applicable":
        logger.info("%s: %s not applicable: %s", report.clip_id, stage.name, report.reason)
    else:
        logger.info("%s: %s done in %.1f s %s", report.clip_id, stage.name, seconds,
                    report.metrics)
    return {"stage": stage.name, "status": report.status, "seconds": seconds,
            "cpu_seconds": cpu, "report": report.model_dump(mode="json")}


def _stage(pipeline: str | None, name: str) -> Stage[Any]:
    return next(s for s in resolve_pipeline(pipeline) if s.name == name)


@task(name="stage", retries=2, retry_delay_seconds=2, retry_condition_fn=_no_retry_on_bad_input,
      task_run_name="{clip_id}:{stage_name}")
def run_stage(stage_name: str, lake_uri: str, target: str, clip_id: str,
              config: dict[str, Any], pipeline: str | None = None) -> dict[str, Any]:
    """One whole stage on one clip, as one task (on a cluster worker when distributed)."""
    stage = _stage(pipeline, stage_name)
    return _execute(stage, lake_uri, target, clip_id, stage.config(config), stage.run)


@task(name="chunk", retries=2, retry_delay_seconds=2, retry_condition_fn=_no_retry_on_bad_input,
      task_run_name="{clip_id}:{stage_name}:{index}")
def run_chunk(stage_name: str, lake_uri: str, clip_id: str, config: dict[str, Any],
              chunk: Any, index: int, stage_root: str | None,
              pipeline: str | None = None) -> Any:
    """One chunk of a chunked stage, writing into the stage's shared staged output."""
    stage = _stage(pipeline, stage_name)
    assert stage.chunked is not None
    writer = Lake(lake_uri).for_stage(stage.name, [(t.zone, t.name) for t in stage.owns],
                                      stage_root=stage_root,
                                      reads=[(t.zone, t.name) for t in stage.reads])
    return stage.chunked.run_chunk(writer, clip_id, stage.config(config), chunk)


def run_chunked_stage(stage: Stage[Any], lake_uri: str, clip_id: str, config: dict[str, Any],
                      pipeline: str | None = None) -> dict[str, Any]:
    """A chunked stage from inside the flow: plan here, the chunks as tasks on the flow's
    task runner (spread over the cluster's workers when distributed), finish here."""
    chunked = stage.chunked
    assert chunked is not None

    def do(writer: Lake, target: str, cfg: BaseModel) -> StageReport:
        plan = chunked.plan(writer, clip_id, cfg)
        if isinstance(plan, StageReport):
            return plan
        futures = [run_chunk.submit(stage.name, lake_uri, clip_id, config, c, i,
                                    writer.stage_root, pipeline) for i, c in enumerate(plan)]
        return chunked.finish(writer, clip_id, cfg, [f.result() for f in futures])

    return _execute(stage, lake_uri, clip_id, clip_id, stage.config(config), do)


def _stage_row(outcome: dict[str, Any]) -> dict[str, Any]:
    rep = outcome.get("report") or {}
    metrics = rep.get("metrics") or {}
    shown = ", ".join(f"{k}={_fmt(v)}" for k, v in list(metrics.items())[:6])
    return {"stage": outcome["stage"], "status": outcome["status"],
            "seconds": round(float(outcome.get("seconds", 0.0)), 2), "metrics": shown,
            "error": outcome.get("error", "")}


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


def _publish_artifacts(lake: Lake, summary: dict[str, Any]) -> None:
    clip_id = summary["clip_id"]
    rows = [_stage_row(o) for o in summary["stages"]]
    create_table_artifact(table=rows, key=_artifact_key("clip", clip_id, "stages"),
                          description=f"Stages of clip {clip_id}: {summary['status']}")
    metric_rows = [
        {"stage": o["stage"], "metric": k, "value": v}
        for o in summary["stages"]
        for k, v in ((o.get("report") or {}).get("metrics") or {}).items()
    ]
    if metric_rows:
        create_table_artifact(
            table=metric_rows, key=_artifact_key("clip", clip_id, "metrics"),
            description="Headline metrics per stage (alignment, registration, QA)")
    try:
        qa = bookkeeping.query(lake, f"SELECT * FROM qa_checks WHERE clip_id = '{clip_id}'")
        if qa.num_rows:
            create_table_artifact(
                table=[{k: v for k, v in r.items() if k != "clip_id"} for r in qa.to_pylist()],
                key=_artifact_key("clip", clip_id, "qa"), description="QA checks")
    except Exception:  # no qa table yet (stage missing or failed early)
        pass
    images = [img for o in summary["stages"] for img in (o.get("report") or {}).get("images", [])]
    lines = [f"# Clip `{clip_id}`: {summary['status']}", "", f"Lake: `{lake.uri}`", ""]
    if summary.get("error"):
        lines += [f"**Error:** {summary['error']}", ""]
    if images:
        lines += ["## Pictures", ""] + [f"- `{p}`" for p in images]
    create_markdown_artifact(markdown="\n".join(lines),
                             key=_artifact_key("clip", clip_id, "summary"))


def _flow_run_name() -> str:
    from prefect.runtime import flow_run

    params = flow_run.parameters or {}
    return f"clip-{Path(str(params.get('clip_dir', 'clip'))).name}"


@flow(name="process-clip", flow_run_name=_flow_run_name, log_prints=True)
def process_clip(clip_dir: str, lake: str, stages: list[str] | None = None,
                 params: dict[str, Any] | None = None, pipeline: str | None = None,
                 refresh_catalog: bool = True) -> dict[str, Any]:
    """Run the stages on one clip folder; quarantine it on bad input.

    ``params`` is a ``PipelineParams`` as a mapping (one section per stage), the form a
    deployment's ``parameters:`` block and the Prefect UI give."""
    logger = get_run_logger()
    the_lake = Lake(lake)
    chosen = select(resolve_pipeline(pipeline), stages)
    run_params = parse_params(params)
    clip_id = peek_clip_id(clip_dir)
    if CLIP_ID.fullmatch(clip_id):  # what a killed earlier run of this clip left behind
        swept = the_lake.sweep(clip_id)
        if swept:
            logger.info("%s: removed %d staging folder(s) of dead runs (%d rolled forward)",
                        clip_id, len(swept.runs), len(swept.rolled_forward))
    summary: dict[str, Any] = {
        "clip_dir": str(clip_dir), "clip_id": clip_id, "status": "ok", "error": None,
        "quarantine_report": None, "stages": [],
    }
    order = {s.name: k for k, s in enumerate(chosen)}

    def fail(stage: str, exc: Exception, quarantine: bool) -> ClipFailed:
        text = error_text(exc)  # bounded: errors quote input
        summary["stages"].append({"stage": stage, "status": "failed", "seconds": 0.0,
                                  "error": text})
        summary["stages"].sort(key=lambda o: order.get(o["stage"], 99))
        _emit(event="stage_end", clip_id=clip_id, stage=stage, status="failed", error=text)
        if isinstance(exc, DeliveryConflict):  # another delivery's id: touch nothing
            summary.update(status="refused", error=text)
            logger.error("clip %s refused: %s", clip_id, text)
            _publish_artifacts(the_lake, summary)
            return ClipFailed(f"clip {clip_id} refused at stage {stage}: {text}", summary)
        if quarantine:
            cid = clip_id if clip_id.startswith(UNREADABLE) else (
                getattr(exc, "clip_id", None) or clip_id)
            inputs_stage = any(s.name == stage and s.input == "clip_dir" for s in chosen)
            report_path = bookkeeping.quarantine(the_lake, cid, exc, stage=stage,
                                                 remove_data=not inputs_stage)
            if f"/{REJECTED}" in report_path:  # the id is another clip's: not that clip
                summary.update(status="rejected", error=text, quarantine_report=report_path)
                logger.error("delivery %s rejected at stage %s (the lake's clip %s is "
                             "untouched): %s (report: %s)", clip_dir, stage, cid, text,
                             report_path)
                _publish_artifacts(the_lake, summary)
                return ClipFailed(f"delivery {clip_dir} rejected at stage {stage}, the lake's "
                                  f"clip {cid} untouched: {text}", summary)
            summary.update(status="quarantined", error=text, quarantine_report=report_path)
            logger.error("clip %s quarantined at stage %s: %s (report: %s)",
                         clip_id, stage, text, report_path)
            _publish_artifacts(the_lake, summary)
            return ClipFailed(f"clip {clip_id} quarantined at stage {stage}: {text}", summary)
        summary.update(status="failed", error=f"{stage}: {text}")
        _publish_artifacts(the_lake, summary)
        return ClipFailed(f"clip {clip_id} failed at stage {stage}: {text}", summary)

    # every stage's effective parameters first: a bad params block fails before any work
    try:
        own = clip_params(clip_dir)
        configs = {s.name: run_params.for_stage(s, own).model_dump(mode="json") for s in chosen}
    except ParamsError as exc:
        err = ClipError(clip_id, f"clip.yaml params: {exc}", path=str(Path(clip_dir) /
                                                                        "clip.yaml"))
        raise fail(chosen[0].name if chosen else "params", err, quarantine=True) from exc
    created = create_progress_artifact(
        progress=0.0, key=_artifact_key("clip", clip_id, "progress"),
        description=f"Stages done for clip {clip_id}")
    # the sync call returns the id itself (the async variant a coroutine)
    progress_id: UUID | None = created if isinstance(created, UUID) else None
    last_progress = time.monotonic()
    for i, stage in enumerate(chosen):
        _emit(event="stage_start", clip_id=clip_id, stage=stage.name, index=i, total=len(chosen))
        target = str(Path(clip_dir).resolve()) if stage.input == "clip_dir" else clip_id
        try:
            if stage.chunked is not None and stage.atomic:
                outcome = run_chunked_stage(stage, lake, clip_id, configs[stage.name], pipeline)
            else:
                outcome = run_stage.submit(stage.name, lake, target, clip_id,
                                           configs[stage.name], pipeline).result()
        except ClipError as exc:
            raise fail(stage.name, exc, quarantine=True) from exc
        except Exception as exc:
            raise fail(stage.name, exc, quarantine=False) from exc
        clip_id = outcome["report"]["clip_id"] or clip_id
        summary["clip_id"] = clip_id
        summary["stages"].append(outcome)
        _emit(event="stage_end", clip_id=clip_id, stage=stage.name, status=outcome["status"],
              seconds=outcome["seconds"], cpu_seconds=outcome.get("cpu_seconds"),
              metrics=outcome["report"].get("metrics", {}),
              reason=outcome["report"].get("reason"))
        # an API round trip (0.05-0.12 s): after the last stage, else at most every
        # PROGRESS_ARTIFACT_EVERY_S, so short stages do not pay one each (#26 fixed cost)
        now = time.monotonic()
        if progress_id is not None and (i + 1 == len(chosen)
                                        or now - last_progress >= PROGRESS_ARTIFACT_EVERY_S):
            update_progress_artifact(progress_id, progress=100.0 * (i + 1) / len(chosen))
            last_progress = now
    summary["stages"].sort(key=lambda o: order.get(o["stage"], 99))
    if refresh_catalog:
        bookkeeping.refresh_catalog(the_lake)
    _publish_artifacts(the_lake, summary)
    return summary


def run_clip_flow(clip_flow: Any, clip_dir: str, *args: Any, **kwargs: Any) -> dict[str, Any]:
    """A clip summary from one ``process_clip`` flow run, whatever it ended as.

    The summary is taken from the run's in-memory return value (or the exception it raised),
    never from its final state: results are not persisted, and a state the engine re-reads
    from the API server (it does when a state proposal is answered late, as on a loaded
    machine with a Dask task runner) carries no data (Prefect's ``MissingResult``)."""
    try:
        return dict(clip_flow(clip_dir, *args, **kwargs))
    except ClipFailed as exc:
        out = exc.summary
        reason: Exception = exc
    except Exception as exc:
        out = {"clip_dir": clip_dir, "clip_id": peek_clip_id(clip_dir), "status": "failed",
               "error": str(exc), "stages": [], "quarantine_report": None}
        reason = exc
    out["state"] = "Failed"
    out["message"] = f"Flow run encountered an exception: {type(reason).__name__}: {reason}"
    return out


@flow(name="process-clips", log_prints=True)
def process_clips(clip_dirs: list[str], lake: str, stages: list[str] | None = None,
                  params: dict[str, Any] | None = None, pipeline: str | None = None,
                  runner: str = "local") -> list[dict[str, Any]]:
    """Process several clip folders; returns one summary per clip (never raises for a clip)."""
    from v2xlake.flows.runners import dask_cluster, make_task_runner, parse_runner

    logger = get_run_logger()
    dirs = [str(Path(d).resolve()) for d in clip_dirs]
    checked = parse_params(params).model_dump(mode="json")  # bad parameters: fail now
    select(resolve_pipeline(pipeline), stages)  # unknown stages / broken imports: fail now
    spec = parse_runner(runner)
    if spec.kind == "local":
        results = []
        for d in dirs:
            results.append(run_clip_flow(process_clip, d, lake, stages, checked, pipeline,
                                         refresh_catalog=False))
    else:
        with dask_cluster(spec) as (address, threads):
            clip_flow = process_clip.with_options(task_runner=make_task_runner(
                f"dask={address}"))

            def one(d: str) -> dict[str, Any]:
                return run_clip_flow(clip_flow, d, lake, stages, checked, pipeline,
                                     refresh_catalog=False)

            # a few clips' flows at a time here; their stages and chunks run on the workers.
            # One flow per worker thread: with twice as many (to fill the 0.5-1 s between a
            # clip's stages) a chunked stage's chunks queued behind other clips' 40 s
            # anonymize tasks (deskew waited 12-43 s) and 4 camera clips on 2 workers took
            # 116.6 s instead of 105.0 s (bench_dask, #26)
            with ThreadPoolExecutor(max_workers=max(1, min(len(dirs), threads))) as pool:
                # each thread runs in a copy of this context: Prefect's settings and client
                # live in context variables, which plain threads do not inherit
                futures = [pool.submit(contextvars.copy_context().run, one, d) for d in dirs]
                results = [f.result() for f in futures]
    bookkeeping.refresh_catalog(Lake(lake))
    bad = [r for r in results if r["status"] != "ok"]
    logger.info("%d clip(s) processed, %d ok, %d not", len(results), len(results) - len(bad),
                len(bad))
    return results
