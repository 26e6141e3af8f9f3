"""Small but real stand-in stages for testing the flow machinery (no tests in this module).

They obey the stage contract (``Stage`` objects whose ``run(lake, clip_dir_or_id, config)``
returns a StageReport, ClipError on bad input, writes only their own tables) and write real
lake tables, so catalog queries, quarantine and releases can be checked independently of the
real stages. Flows name them as ``pipeline="test_flows_fakestages:FAKE_PIPELINE"``, which
Dask workers and worker processes import by name (tests put ``tests/`` on ``PYTHONPATH``).
"""

from __future__ import annotations

import json
import os
import time
import uuid
from pathlib import Path

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict

from v2xlake.schemas.arrow import rows_to_table
from v2xlake.schemas.errors import ClipError
from v2xlake.schemas.stage import OutputFile, Stage, StageReport, tables
from v2xlake.schemas.tables import AnnotationRow, ClipRow, QaCheckRow
from v2xlake.storage.lake import Lake


class FakeConfig(BaseModel):
    """A parameter so that tests can see parameters reach a stage and its manifest."""

    model_config = ConfigDict(extra="forbid")

    n_objects: int | None = None


def make_fake_clip(root: Path, clip_id: str, *, location: str = "town", weather: str = "clear",
                   lighting: str = "day", corrupt: bool = False, n_objects: int = 12) -> Path:
    d = root / clip_id
    d.mkdir(parents=True, exist_ok=True)
    (d / "clip.yaml").write_text(yaml.safe_dump({
        "clip_id": clip_id, "location": location, "road_type": "local", "weather": weather,
        "lighting": lighting, "work_zone": False, "n_objects": n_objects}))
    (d / "red.bin").write_bytes(np.arange(1000, dtype=np.float32).tobytes())
    if corrupt:
        (d / "CORRUPT").write_text("the INS topic is empty")
    return d


def _count_call(lake: Lake, stage: str, clip_id: str) -> None:
    lake.write_json(lake.path("fake_calls", stage, clip_id, f"{uuid.uuid4().hex}.json"),
                    {"t": time.time()})


def call_count(lake: Lake, stage: str, clip_id: str) -> int:
    return len(lake.list_files(lake.path("fake_calls", stage, clip_id), ".json"))


def fake_ingest(lake: Lake, clip_dir: str | Path, config: FakeConfig | None = None) -> StageReport:
    meta = yaml.safe_load((Path(clip_dir) / "clip.yaml").read_text())
    cid = meta["clip_id"]
    _count_call(lake, "ingest", cid)
    for f in sorted(Path(clip_dir).iterdir()):
        lake.write_bytes(lake.path("landing", cid, f.name), f.read_bytes())
    row = ClipRow(clip_id=cid, location=meta["location"], road_type=meta["road_type"],
                  weather=meta["weather"], lighting=meta["lighting"], work_zone=False,
                  n_agents=2, reference_agent="red", source="simulated", status="ok",
                  duration_s=(Path(clip_dir) / "red.bin").stat().st_size / 2000.0)
    rows_in: list[BaseModel] = [row]
    path, rows = lake.write_table("clean", "clips", rows_to_table(ClipRow, rows_in), clip_id=cid)
    return StageReport(stage="ingest", clip_id=cid, outputs=[OutputFile(path=path, rows=rows)],
                       metrics={"n_files": float(len(list(Path(clip_dir).iterdir())))})


def fake_qa(lake: Lake, clip_id: str, config: FakeConfig | None = None) -> StageReport:
    _count_call(lake, "qa", clip_id)
    corrupt = lake.exists(lake.path("landing", clip_id, "CORRUPT"))
    row = QaCheckRow(clip_id=clip_id, agent_id="red", sensor="INS", check="ins_present",
                     passed=not corrupt, severity="error", value=0.0 if corrupt else 1.0,
                     threshold=1.0, detail="INS messages present")
    qa_rows: list[BaseModel] = [row]
    path, rows = lake.write_table("raw", "qa_checks", rows_to_table(QaCheckRow, qa_rows),
                                  clip_id=clip_id)
    if corrupt:
        raise ClipError(clip_id, "no INS messages", agent_id="red", topic="/red/ins", stage="qa")
    return StageReport(stage="qa", clip_id=clip_id, outputs=[OutputFile(path=path, rows=rows)],
                       metrics={"checks_failed": 0.0, "pid": float(os.getpid())})


def fake_annotate(lake: Lake, clip_id: str, config: FakeConfig | None = None) -> StageReport:
    """Boxes on a ring around the ego vehicle, classes cycling (release statistics need them)."""
    _count_call(lake, "annotate", clip_id)
    meta = yaml.safe_load(lake.read_bytes(lake.path("landing", clip_id, "clip.yaml")))
    n = config.n_objects if config and config.n_objects is not None else \
        int(meta.get("n_objects", 12))
    rng = np.random.default_rng(abs(hash(clip_id)) % 2**32)
    classes = ["car", "pedestrian", "truck", "bicycle"]
    rows: list[BaseModel] = []
    for i in range(n):
        r = float(rng.uniform(3, 60))
        a = float(rng.uniform(0, 2 * np.pi))
        rows.append(AnnotationRow(
            clip_id=clip_id, agent_id="red", sensor="LIDAR_TOP", frame_idx=0, t_ns=100_000_000,
            instance_id=f"{clip_id}-{i}", category=classes[i % len(classes)],
            cx=r * np.cos(a), cy=r * np.sin(a), cz=0.0, w=1.8, l=4.5, h=1.5,
            qw=1.0, qx=0.0, qy=0.0, qz=0.0, links=[], num_lidar_pts=10))
    table = rows_to_table(AnnotationRow, rows)
    path, nrows = lake.write_table("clean", "annotations", table, clip_id=clip_id,
                                   agent_id="red")
    blob = lake.write_blob("clean", lake.blob_key(clip_id, "red", "CAM_FRONT", 0),
                           json.dumps({"fake_png_for": clip_id}).encode())
    return StageReport(stage="annotate", clip_id=clip_id,
                       outputs=[OutputFile(path=path, rows=nrows)],
                       metrics={"n_boxes": float(table.num_rows)},
                       images=[lake.blob_path("clean", blob)])



def fake_flaky(lake: Lake, clip_id: str, config: FakeConfig | None = None) -> StageReport:
    """Fails with a transient error on its first call per clip (the task's retry must help)."""
    _count_call(lake, "flaky", clip_id)
    if call_count(lake, "flaky", clip_id) == 1:
        raise OSError("transient: object store timed out")
    return StageReport(stage="flaky", clip_id=clip_id, metrics={"pid": float(os.getpid())})


FAKE_INGEST = Stage(name="ingest", config_model=FakeConfig, input="clip_dir", reads=(),
                    owns=tables("clean", "clips"), run=fake_ingest)
FAKE_QA = Stage(name="qa", config_model=FakeConfig, reads=tables("clean", "clips"),
                owns=tables("raw", "qa_checks"), run=fake_qa)
FAKE_ANNOTATE = Stage(name="annotate", config_model=FakeConfig,
                      reads=tables("clean", "clips"), owns=tables("clean", "annotations"),
                      run=fake_annotate)
FAKE_FLAKY = Stage(name="flaky", config_model=FakeConfig, reads=(), owns=(), run=fake_flaky)
FAKE_PIPELINE = (FAKE_INGEST, FAKE_QA, FAKE_ANNOTATE)
FLAKY_PIPELINE = (*FAKE_PIPELINE, FAKE_FLAKY)
FAKES = "test_flows_fakestages:FAKE_PIPELINE"
