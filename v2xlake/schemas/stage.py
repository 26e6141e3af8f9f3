"""The stage contract: what a stage is, what it returns, and how exports look.

Every stage of the per-clip pipeline is one package ``tasks/<stage>/`` whose ``stage.py``
exports a :class:`Stage` object. The flow (``flows/pipeline.py``) imports those objects
directly, so a stage whose module fails to import fails the command before any clip is
touched, and the call chain from the flow into every stage is plain Python.

A stage declares the tables it reads and the tables it owns. Ownership is the single-writer
rule of the lake (``schemas.tables.TABLE_OWNERS``): a stage writes only its own tables, so a
re-run of one stage can never drop columns or rows another stage put there, and the manifest
can decide freshness from the checksums of exactly the files a stage read.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Generic, Literal, Protocol, TypeVar

from pydantic import BaseModel, Field

if TYPE_CHECKING:  # type-only: schemas never imports storage at run time
    from v2xlake.storage.lake import Lake

Zone = Literal["raw", "clean"]
StageStatus = Literal["done", "not_applicable"]


class OutputFile(BaseModel):
    path: str
    rows: int | None = None
    checksum: str | None = None  # storage.checksum: '<algorithm>:<hex>'


class StageReport(BaseModel):
    """Result of one stage on one clip: files written, headline metrics, pictures made.

    ``status`` is ``not_applicable`` when the clip lacks what the stage needs (no pose, a
    single agent for registration, no annotations): that is a fact about the recording, not
    a failure, so nothing is quarantined and ``reason`` says why.
    """

    stage: str
    clip_id: str
    status: StageStatus = "done"
    reason: str | None = None
    outputs: list[OutputFile] = Field(default_factory=list)
    metrics: dict[str, float] = Field(default_factory=dict)
    images: list[str] = Field(default_factory=list)
    notes: list[str] = Field(default_factory=list)

    @classmethod
    def not_applicable(cls, stage: str, clip_id: str, reason: str) -> StageReport:
        return cls(stage=stage, clip_id=clip_id, status="not_applicable", reason=reason)


@dataclass(frozen=True)
class TableRef:
    """One lake table in one zone, e.g. ``TableRef("clean", "lidar_points")``."""

    zone: Zone
    name: str

    def __str__(self) -> str:
        return f"{self.zone}.{self.name}"


def tables(zone: Zone, *names: str) -> tuple[TableRef, ...]:
    return tuple(TableRef(zone, n) for n in names)


# The raw-zone tables ingest writes; anonymize writes each of them again into the clean zone
# (relative time, local ENU, blurred images), except those that never leave raw. Here, not
# in ``schemas/tables.py`` beside the row models, because both stages' declarations
# (``StageDeclaration``) name them and must not import pyarrow.
INGEST_TABLES = ("clips", "agents", "sensors", "calibrated_sensors", "ins", "ego_poses", "imu",
                 "gnss", "lidar_frames", "lidar_points", "camera_frames", "annotations",
                 "radar_frames", "radar_points")
RAW_ONLY_TABLES = ("ins",)


@dataclass(frozen=True)
class StageDeclaration:
    """What a stage package says about itself in its ``__init__.py`` (as ``DECLARATION``),
    readable without importing any other module of the package: its name and the tables it
    owns. The registry (``schemas/registry.py``) finds the package from the stage list or
    an entry point; by the package shape, its parameters are the one ``StageConfig`` of
    ``<package>.config`` and its Stage object is ``<package>.stage.<stage_object>``.

    WHY a declaration apart from the Stage object: the owners of the lake's tables, the
    parameter sections and ``v2xlake params show`` must be known without importing a
    stage's numeric code (seconds); the Stage object takes ``name`` and ``owns`` from here
    (``tests/test_stage_contract.py`` checks that the two agree)."""

    name: str
    owns: tuple[TableRef, ...]
    stage_object: str = ""  # the attribute of ``<package>.stage``; default: NAME in capitals

    def __post_init__(self) -> None:
        if not self.stage_object:
            object.__setattr__(self, "stage_object", self.name.upper())


C = TypeVar("C", bound=BaseModel)


@dataclass(frozen=True)
class Chunked(Generic[C]):
    """How a stage splits one clip's work so a cluster can share it.

    ``plan`` (in the flow's process) lists picklable chunk descriptions, or returns a
    not-applicable report; ``run_chunk`` (anywhere: a Dask worker) processes one chunk,
    writes its share of the stage's output and returns a picklable partial result;
    ``finish`` (in the flow's process) merges the partial results into the report and
    writes what belongs to the whole clip. Run one after another, the three give the same
    output as the stage's ``run``.
    """

    plan: Callable[[Lake, str, C], list[Any] | StageReport]
    run_chunk: Callable[[Lake, str, C, Any], Any]
    finish: Callable[[Lake, str, C, list[Any]], StageReport]


@dataclass(frozen=True)
class Stage(Generic[C]):
    """One pipeline stage.

    ``run(lake, target, config)`` gets the clip folder for ``input="clip_dir"`` (ingest) and
    the clip id otherwise. ``config`` is an instance of ``config_model`` (a pydantic model
    whose every field is a user-settable parameter; its hash enters the manifest).
    """

    name: str
    config_model: type[C]
    reads: tuple[TableRef, ...]
    owns: tuple[TableRef, ...]
    run: Callable[[Lake, str, C], StageReport]
    input: Literal["clip_dir", "clip_id"] = "clip_id"
    doc: str = ""
    # the flow stages this stage's Parquet output and publishes it when run returns, so a
    # killed run never shows half of it; False for stages that stage and publish themselves
    atomic: bool = True
    chunked: Chunked[Any] | None = None  # how a cluster shares one clip's work, if it can

    def config(self, values: dict[str, Any] | BaseModel | None = None) -> C:
        """The stage's config from user values (unknown keys are an error)."""
        if isinstance(values, self.config_model):
            return values
        if isinstance(values, BaseModel):
            values = values.model_dump()
        return self.config_model.model_validate(values or {})


class Exporter(Protocol):
    """A release format: one call over a set of clips into one output folder.

    ``splits`` maps scene (clip) ids to split names for the formats that carry splits.
    """

    name: str
    config_model: type[BaseModel]

    def export(self, lake: Lake, clip_ids: list[str], out: str, config: BaseModel,
               splits: dict[str, str] | None = None) -> list[StageReport]: ...
