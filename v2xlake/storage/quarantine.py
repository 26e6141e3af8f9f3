"""Quarantine: a failed clip gets a human-readable report and disappears from the zones.

``quarantine/<clip_id>/report.json`` says which stage failed, why (the ``ClipError``'s
clip / agent / topic / file / reason, or the failed QA checks with value and threshold), and
when. The clip's raw and clean partitions and blobs are removed so the catalog never shows a
half-published clip; the landing copy (the bags as delivered) stays for diagnosis, as do the
other clips, which are untouched.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

from pydantic import BaseModel

from v2xlake.storage.lake import Lake

REPORT = "report.json"


def report_path(lake: Lake, clip_id: str) -> str:
    return lake.path("quarantine", clip_id, REPORT)


def _check_dict(c: Any) -> dict[str, Any]:
    return c.model_dump(mode="json") if isinstance(c, BaseModel) else dict(c)


def quarantine(lake: Lake, clip_id: str, error: BaseException | str | None = None,
               checks: Sequence[Any] = (), *, stage: str | None = None,
               zones: Sequence[str] = ("raw", "clean")) -> dict[str, Any]:
    """Write the report, remove the clip's partitions from ``zones``; returns the report."""
    failed = [_check_dict(c) for c in (checks or getattr(error, "checks", None) or ())]
    if isinstance(error, BaseException) and hasattr(error, "to_dict"):  # tasks.errors.ClipError
        err: dict[str, Any] | None = error.to_dict()
        reason = str(error)
        stage = stage or getattr(error, "stage", None)
    elif isinstance(error, str):
        err, reason = {"message": error}, error
    elif error is not None:
        err = {"type": type(error).__name__, "message": str(error)}
        reason = str(error)
    else:
        err = None
    prev = read_report(lake, clip_id)
    if not failed and prev and prev.get("checks") and (stage is None or prev.get("stage") == stage):
        failed = list(prev["checks"])  # the flow re-quarantining a QA failure keeps the checks
    failed_err = [c for c in failed if not c.get("passed") and c.get("severity") == "error"]
    if error is None:
        reason = "; ".join(
            f"{c['check']}" + (f" ({c['agent_id']}/{c['sensor']})" if c.get("sensor") else
                               f" ({c['agent_id']})" if c.get("agent_id") else "")
            + f": {c['detail']}" for c in failed_err) or "quarantined"
    report = {
        "clip_id": clip_id,
        "stage": stage,
        "reason": reason,
        "error": err,
        "failed_checks": failed_err,
        "checks": failed,
        "quarantined_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "removed_zones": list(zones),
        "landing": lake.path("landing", clip_id),
    }
    lake.write_json(report_path(lake, clip_id), report)
    for zone in zones:
        lake.delete_clip(zone, clip_id)
    return report


def is_quarantined(lake: Lake, clip_id: str) -> bool:
    return lake.exists(report_path(lake, clip_id))


def read_report(lake: Lake, clip_id: str) -> dict[str, Any] | None:
    p = report_path(lake, clip_id)
    return lake.read_json(p) if lake.exists(p) else None


def release(lake: Lake, clip_id: str) -> None:
    """Remove the quarantine report (after the input was fixed, before reprocessing)."""
    lake.delete_dir(lake.path("quarantine", clip_id))
