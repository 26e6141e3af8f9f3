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

from v2xlake.schemas.errors import bounded
from v2xlake.storage.lake import Lake, safe_name

REPORT = "report.json"
#: Where the report of a delivery that failed at intake goes when the lake already holds a
#: clip under the id it claims: ``quarantine/_rejected-<id>/``. Its data is untouched and
#: still served, so it is not quarantined, and a hostile or broken clip.yaml claiming the
#: id must not make it look so (no clip id starts with "_").
REJECTED = "_rejected-"


def report_path(lake: Lake, clip_id: str) -> str:
    """The report of ``clip_id`` (a name too long for a folder is shortened with a hash)."""
    return lake.path("quarantine", safe_name(clip_id), REPORT)


def holds_clip(lake: Lake, clip_id: str) -> bool:
    """Whether the lake already has a clip under this id: one whose ingest finished (its
    manifest). A landing copy alone is not one: ingest copies a delivery in before reading
    its bags, so a first delivery that fails there leaves one."""
    return lake.exists(lake.path("manifests", safe_name(clip_id), "ingest.json"))


def _check_dict(c: Any) -> dict[str, Any]:
    return c.model_dump(mode="json") if isinstance(c, BaseModel) else dict(c)


def quarantine(lake: Lake, clip_id: str, error: BaseException | str | None = None,
               checks: Sequence[Any] = (), *, stage: str | None = None,
               zones: Sequence[str] = ("raw", "clean")) -> dict[str, Any]:
    """Write the report, remove the clip's partitions from ``zones``; returns the report
    (``report_id``: the folder it went to under ``quarantine/``).

    ``zones=()`` is a delivery that failed at intake (nothing of it was published): when the
    lake already holds a clip under the id it claims, the report goes to
    ``quarantine/_rejected-<id>/`` instead, so the clip the lake has is never reported as
    quarantined by someone else's delivery. Every text in the report is bounded
    (``schemas.errors.bounded``): reasons quote input."""
    failed = [_check_dict(c) for c in (checks or getattr(error, "checks", None) or ())]
    if isinstance(error, BaseException) and hasattr(error, "to_dict"):  # tasks.errors.ClipError
        err: dict[str, Any] | None = {k: bounded(v) if isinstance(v, str) else v
                                      for k, v in error.to_dict().items()}
        reason = bounded(error)
        stage = stage or getattr(error, "stage", None)
    elif isinstance(error, str):
        reason = bounded(error)
        err = {"message": reason}
    elif error is not None:
        reason = bounded(error)
        err = {"type": type(error).__name__, "message": reason}
    else:
        err = None
    report_id = clip_id
    if not zones and not clip_id.startswith("_") and holds_clip(lake, clip_id):
        report_id = REJECTED + clip_id
    prev = read_report(lake, report_id)
    if not failed and prev and prev.get("checks") and (stage is None or prev.get("stage") == stage):
        failed = list(prev["checks"])  # the flow re-quarantining a QA failure keeps the checks
    failed_err = [c for c in failed if not c.get("passed") and c.get("severity") == "error"]
    if error is None:
        reason = "; ".join(
            f"{c['check']}" + (f" ({c['agent_id']}/{c['sensor']})" if c.get("sensor") else
                               f" ({c['agent_id']})" if c.get("agent_id") else "")
            + f": {c['detail']}" for c in failed_err) or "quarantined"
        reason = bounded(reason)
    report = {
        "clip_id": clip_id,
        "report_id": safe_name(report_id),
        "stage": stage,
        "reason": reason,
        "error": err,
        "failed_checks": failed_err,
        "checks": failed,
        "quarantined_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "removed_zones": list(zones),
        "landing": lake.path("landing", clip_id),
    }
    if report_id != clip_id:
        report["reason"] = bounded(
            f"delivery refused at intake; the clip {clip_id} the lake already holds is "
            f"untouched: {reason}")
    lake.write_json(report_path(lake, report_id), report)
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
    lake.delete_dir(lake.path("quarantine", safe_name(clip_id)))
