"""The clip's optional annotation file (``AnnotationFile``) -> ``annotations`` rows per agent.

Boxes are checked against what was ingested: the agent must exist and the frame index must
name a LiDAR frame of that sensor, so a label file from another version of the clip is caught
here and not when a release is evaluated.
"""

from __future__ import annotations

from pathlib import Path

import pyarrow as pa

from v2xlake.schemas.annotation import AnnotationFile
from v2xlake.schemas.tables import AnnotationRow
from v2xlake.tasks.ingest.rows import table_of


def load_annotations(path: Path, clip_id: str) -> AnnotationFile:
    ann = AnnotationFile.load(path)
    if ann.clip_id != clip_id:
        raise ValueError(f"annotation file is for clip {ann.clip_id!r}, not {clip_id!r}")
    return ann


def annotation_tables(ann: AnnotationFile, frames: dict[tuple[str, str], int]
                      ) -> dict[str, pa.Table]:
    """Per agent table; ``frames[(agent, sensor)]`` = number of ingested LiDAR frames."""
    rows: dict[str, list[AnnotationRow]] = {}
    for a in ann.annotations:
        n = frames.get((a.agent_id, a.sensor))
        if n is None:
            raise ValueError(f"annotation of instance {a.instance_id!r} names agent "
                             f"{a.agent_id!r} sensor {a.sensor!r}, which the clip does not have")
        if a.frame_idx >= n:
            raise ValueError(f"annotation of instance {a.instance_id!r} names frame "
                             f"{a.frame_idx} of {a.agent_id}/{a.sensor}, which has {n} frames")
        c, s, q = a.box.center, a.box.size, a.box.rotation
        v: list[float | None] = list(a.velocity) if a.velocity else [None, None, None]
        rows.setdefault(a.agent_id, []).append(AnnotationRow(
            clip_id=ann.clip_id, agent_id=a.agent_id, sensor=a.sensor, frame_idx=a.frame_idx,
            t_ns=a.t_ns, instance_id=a.instance_id, category=a.category.value,
            cx=c[0], cy=c[1], cz=c[2], w=s[0], l=s[1], h=s[2],
            qw=q[0], qx=q[1], qy=q[2], qz=q[3], vx=v[0], vy=v[1], vz=v[2],
            links=list(a.links), num_lidar_pts=a.num_lidar_pts))
    return {agent: table_of(AnnotationRow, r) for agent, r in rows.items()}
