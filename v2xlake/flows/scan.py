"""The landing-zone scan run by the scheduled deployment.

New clips are delivered as folders ``<inbox>/<name>/clip.yaml`` (+ bags); the default inbox
is ``<lake>/landing/incoming`` for a local lake (an S3 lake needs a local ``inbox``: bags are
read through rosbags from a file system). A folder is new when its clip id has neither flow
records nor a quarantine report in the lake, and complete when it has not changed for
``settle_seconds`` (a copy still in progress is left for the next scan). Each scan first
sweeps what killed runs left in the lake (``Lake.sweep``: staging of dead runs finished or
dropped, their temporary files and release builds removed; live runs' work kept).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from prefect import flow, get_run_logger

from v2xlake.flows import bookkeeping
from v2xlake.flows.pipeline import peek_clip_id, process_clips
from v2xlake.storage.lake import Lake


def default_inbox(lake: Lake) -> Path:
    if not lake.is_local:
        raise ValueError("an S3 lake needs a local inbox directory (--inbox / inbox=)")
    return Path(lake.path("landing", "incoming"))


def find_new_clips(lake: Lake, inbox: Path, settle_seconds: float = 2.0) -> list[Path]:
    seen = bookkeeping.processed_clip_ids(lake)
    now = time.time()
    out = []
    for yaml_path in sorted(Path(inbox).glob("*/clip.yaml")):
        clip_dir = yaml_path.parent
        if peek_clip_id(clip_dir) in seen:
            continue
        newest = max((p.stat().st_mtime for p in clip_dir.rglob("*") if p.is_file()),
                     default=now)
        if now - newest < settle_seconds:
            continue
        out.append(clip_dir)
    return out


@flow(name="scan-landing", log_prints=True)
def scan_landing(lake: str, inbox: str | None = None, stages: list[str] | None = None,
                 params: dict[str, Any] | None = None, pipeline: str | None = None,
                 runner: str = "local",
                 settle_seconds: float = 2.0) -> list[dict[str, Any]]:
    """Process every newly arrived clip folder in the inbox; returns their summaries."""
    logger = get_run_logger()
    the_lake = Lake(lake)
    swept = the_lake.sweep()  # what runs killed since the last scan left behind
    if swept:
        logger.info("swept %d run folder(s) (%d rolled forward) and %d temporary file(s) "
                    "of dead runs", len(swept.runs), len(swept.rolled_forward),
                    len(swept.files))
    box = Path(inbox) if inbox else default_inbox(the_lake)
    box.mkdir(parents=True, exist_ok=True)
    new = find_new_clips(the_lake, box, settle_seconds)
    if not new:
        logger.info("no new clips in %s", box)
        return []
    logger.info("%d new clip(s) in %s: %s", len(new), box, [p.name for p in new])
    return process_clips([str(p) for p in new], lake, stages, params, pipeline, runner)
