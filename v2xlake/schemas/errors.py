"""The one error type a stage raises for bad input.

It always names the clip, agent, topic (or file) and reason, because the person reading it
is looking at a quarantine report for one of hundreds of clips and must know where to look.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

#: Longest error text (characters) the project renders anywhere: a ClipError's reason, a
#: quarantine report, a log line, the CLI. Reasons are written from untrusted input (a
#: clip.yaml value, a field name, a bag's type name); a real one is a line or a few.
MAX_ERROR_CHARS = 2000


def bounded(text: object, limit: int = MAX_ERROR_CHARS) -> str:
    """``str(text)`` cut to at most ``limit`` characters (saying how much was cut): every
    error text that may quote input goes through this before it is shown, logged or
    written. Only ``str`` is called, once, on what the caller passes: a caller holding an
    object whose ``str`` itself may be unbounded (a pydantic error of a huge input) must
    not pass that object, but the text it builds with bounded parts."""
    s = text if isinstance(text, str) else str(text)
    if len(s) <= limit:
        return s
    keep = max(limit - 40, 0)
    return f"{s[:keep]} ... [{len(s) - keep:,} more characters]"


def error_text(exc: BaseException, limit: int = MAX_ERROR_CHARS) -> str:
    """One bounded line for any exception: a ClipError's own message, else
    ``Type: message``."""
    if isinstance(exc, ClipError):
        return bounded(str(exc), limit)
    return bounded(f"{type(exc).__name__}: {exc}", limit)


class ClipError(Exception):
    """Bad input in one clip: quarantine the clip, keep going with the others."""

    def __init__(
        self,
        clip_id: str,
        reason: str,
        *,
        agent_id: str | None = None,
        topic: str | None = None,
        path: str | None = None,
        stage: str | None = None,
        checks: Sequence[Any] = (),
    ) -> None:
        reason = bounded(reason)
        self.clip_id, self.reason = clip_id, reason
        self.checks = list(checks)  # QA findings behind the error, for the quarantine report
        self.agent_id, self.topic, self.path, self.stage = agent_id, topic, path, stage
        where = [f"clip {bounded(clip_id, 200)}"]
        if agent_id:
            where.append(f"agent {bounded(agent_id, 200)}")
        if topic:
            where.append(f"topic {bounded(topic, 500)}")
        if path:
            where.append(f"file {bounded(path, 1000)}")
        if stage:
            where.insert(0, f"[{stage}]")
        super().__init__(f"{', '.join(where)}: {reason}")

    def __reduce__(self) -> tuple[Any, ...]:
        """Picklable with its fields (it crosses process boundaries: Dask workers)."""
        return (_rebuild, (self.clip_id, self.reason, self.agent_id, self.topic, self.path,
                           self.stage, self.checks))

    def to_dict(self) -> dict[str, str | None]:
        return {
            "clip_id": self.clip_id, "agent_id": self.agent_id, "topic": self.topic,
            "path": self.path, "stage": self.stage, "reason": self.reason, "message": str(self),
        }


class DeliveryConflict(ClipError):
    """A delivery whose bags differ from those already in the lake under the same clip id.

    A clip's identity is its id plus the checksums of its delivered bags: the new delivery
    is refused (the flow does not quarantine, so the existing clip's data is untouched)
    unless the operator replaces it explicitly (``ingest.replace_existing``)."""

    def __reduce__(self) -> tuple[Any, ...]:
        return (_rebuild_conflict, (self.clip_id, self.reason, self.path))


def _rebuild_conflict(clip_id: str, reason: str, path: str | None) -> DeliveryConflict:
    return DeliveryConflict(clip_id, reason, path=path, stage="ingest")


def _rebuild(clip_id: str, reason: str, agent_id: str | None, topic: str | None,
             path: str | None, stage: str | None, checks: list[Any]) -> ClipError:
    return ClipError(clip_id, reason, agent_id=agent_id, topic=topic, path=path, stage=stage,
                     checks=checks)
