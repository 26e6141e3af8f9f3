"""What every stage returns, so that flows, manifests and the demo treat stages alike."""

from __future__ import annotations

from pydantic import BaseModel, Field


class OutputFile(BaseModel):
    path: str
    rows: int | None = None
    checksum: str | None = None  # storage.checksum: '<algorithm>:<hex>'


class StageReport(BaseModel):
    """Result of one stage on one clip: files written, headline metrics, pictures made."""

    stage: str
    clip_id: str
    outputs: list[OutputFile] = Field(default_factory=list)
    metrics: dict[str, float] = Field(default_factory=dict)
    images: list[str] = Field(default_factory=list)
    notes: list[str] = Field(default_factory=list)
