"""The one error type a stage raises for bad input.

It always names the clip, agent, topic (or file) and reason, because the person reading it
is looking at a quarantine report for one of hundreds of clips and must know where to look.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any


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
        self.clip_id, self.reason = clip_id, reason
        self.checks = list(checks)  # QA findings behind the error, for the quarantine report
        self.agent_id, self.topic, self.path, self.stage = agent_id, topic, path, stage
        where = [f"clip {clip_id}"]
        if agent_id:
            where.append(f"agent {agent_id}")
        if topic:
            where.append(f"topic {topic}")
        if path:
            where.append(f"file {path}")
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
