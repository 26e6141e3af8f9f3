"""A small raw zone written directly with the Lake API (ingest is another stage's job).

Two agents drive ~10 m/s near Shanghai for one second; GNSS-epoch time stamps follow the PPS
model; each agent has two camera frames with real faces and rendered plates pasted in.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np
import pyarrow as pa
from pydantic import BaseModel

from v2xlake.schemas.arrow import columns_to_table
from v2xlake.schemas.arrow import rows_to_table as _rows_to_table
from v2xlake.schemas.tables import (
    AgentRow,
    AnnotationRow,
    CalibratedSensorRow,
    CameraFrameRow,
    ClipRow,
    GnssRow,
    ImuRow,
    InsRow,
    LidarFrameRow,
    LidarPointRow,
    QaCheckRow,
    SensorRow,
)
from v2xlake.storage.lake import Lake
from v2xlake.tasks.anonymize.evaluate import TrueBox, synth_scene
from v2xlake.tasks.geodesy import LocalFrame, matrix_to_attitude

CLIP = "clip_test_0001"
T_PPS = 1_735_000_000 * 10**9  # a GNSS second in Dec 2024, as ns
LAT0, LON0, ALT0 = 31.2304, 121.4737, 12.5
AGENTS = {"red": (0.0, 0.0), "black": (-15.0, 3.5)}
IMG_W, IMG_H = 640, 360


def rows_to_table(model: type[BaseModel], rows: Sequence[BaseModel]) -> pa.Table:
    return _rows_to_table(model, list[BaseModel](rows))


def _write(
    lake: Lake, table: str, t: pa.Table, agent: str | None = None, row_group_by: str | None = None
) -> None:
    lake.write_table("raw", table, t, clip_id=CLIP, agent_id=agent, row_group_by=row_group_by)


def build_raw_clip(lake: Lake, n_images: int = 2) -> dict[tuple[str, int], list[TrueBox]]:
    """Write every raw table for CLIP; returns the true face/plate boxes per (agent, frame)."""
    frame = LocalFrame(LAT0, LON0)
    _write(
        lake,
        "clips",
        rows_to_table(
            ClipRow,
            [
                ClipRow(
                    clip_id=CLIP,
                    location="test town",
                    road_type="urban",
                    weather="clear",
                    lighting="day",
                    work_zone=False,
                    n_agents=2,
                    reference_agent="red",
                    duration_s=1.0,
                    source="simulated",
                    status="ok",
                )
            ],
        ),
    )
    truth: dict[tuple[str, int], list[TrueBox]] = {}
    for ai, (agent, (x_off, y_off)) in enumerate(AGENTS.items()):
        _write(
            lake,
            "agents",
            rows_to_table(
                AgentRow,
                [
                    AgentRow(
                        clip_id=CLIP,
                        agent_id=agent,
                        kind="vehicle",
                        role="reference" if agent == "red" else "cooperative",
                        has_ins=True,
                    )
                ],
            ),
            agent,
        )
        _write(
            lake,
            "sensors",
            rows_to_table(
                SensorRow,
                [
                    SensorRow(
                        clip_id=CLIP,
                        agent_id=agent,
                        sensor=s,
                        modality=m,
                        topic=f"/{agent}/{s.lower()}",
                        msg_type="x",
                        n_messages=10,
                    )
                    for s, m in (("LIDAR_TOP", "lidar"), ("CAM_FRONT", "camera"))
                ],
            ),
            agent,
        )
        _write(
            lake,
            "calibrated_sensors",
            rows_to_table(
                CalibratedSensorRow,
                [
                    CalibratedSensorRow(
                        clip_id=CLIP,
                        agent_id=agent,
                        sensor="CAM_FRONT",
                        modality="camera",
                        tx=1.5,
                        ty=0.0,
                        tz=1.6,
                        qw=0.5,
                        qx=-0.5,
                        qy=0.5,
                        qz=-0.5,
                        width=IMG_W,
                        height=IMG_H,
                        fx=500.0,
                        fy=500.0,
                        cx=320.0,
                        cy=180.0,
                        distortion_model="none",
                        distortion=[],
                        source="clip.yaml",
                    )
                ],
            ),
            agent,
        )
        # INS: 125 Hz, heading east-north-east at 10 m/s, slight climb; first fix 3 ms after PPS
        t_ins = T_PPS + 3_000_000 * (ai + 1) + np.arange(125) * 8_000_000
        s = (t_ins - T_PPS) / 1e9
        heading = np.deg2rad(60.0)  # azimuth from north, clockwise
        e = x_off + 10 * s * np.sin(heading)
        n = y_off + 10 * s * np.cos(heading)
        u = ALT0 + 0.1 * s
        lat, lon, alt = frame.to_geodetic(np.stack([e, n, u], -1))
        R = np.broadcast_to(np.eye(3), (len(s), 3, 3))
        yaw = np.pi / 2 - heading
        Rz = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
        roll, pitch, az = matrix_to_attitude(Rz @ R)
        _write(
            lake,
            "ins",
            columns_to_table(
                InsRow,
                {
                    "clip_id": [CLIP] * len(s),
                    "agent_id": [agent] * len(s),
                    "t_ns": t_ins,
                    "lat": lat,
                    "lon": lon,
                    "alt": alt,
                    "roll": roll,
                    "pitch": pitch,
                    "azimuth": az,
                    "ve": np.full(len(s), 10 * np.sin(heading)),
                    "vn": np.full(len(s), 10 * np.cos(heading)),
                    "vu": np.full(len(s), 0.1),
                    "rtk_status": np.full(len(s), 2),
                },
            ),
            agent,
        )
        t_imu = T_PPS + np.arange(100) * 10_000_000
        _write(
            lake,
            "imu",
            columns_to_table(
                ImuRow,
                {
                    "clip_id": [CLIP] * 100,
                    "agent_id": [agent] * 100,
                    "sensor": ["IMU"] * 100,
                    "t_ns": t_imu,
                    **{k: np.zeros(100) for k in ("wx", "wy", "wz", "ax", "ay")},
                    "az": np.full(100, 9.81),
                },
            ),
            agent,
        )
        t_g = T_PPS + np.arange(10) * 100_000_000
        glat, glon, galt = frame.to_geodetic(
            np.stack([e[::12][:10], n[::12][:10], u[::12][:10]], -1)
        )
        _write(
            lake,
            "gnss",
            columns_to_table(
                GnssRow,
                {
                    "clip_id": [CLIP] * 10,
                    "agent_id": [agent] * 10,
                    "t_ns": t_g,
                    "lat": glat,
                    "lon": glon,
                    "alt": galt,
                    "status": np.full(10, 2),
                    "sigma_h": np.full(10, 0.02),
                },
            ),
            agent,
        )
        # LiDAR: 10 frames, 50 points each, per-point time over the 100 ms sweep
        nf, npf = 10, 50
        t_start = T_PPS + np.arange(nf) * 100_000_000
        _write(
            lake,
            "lidar_frames",
            columns_to_table(
                LidarFrameRow,
                {
                    "clip_id": [CLIP] * nf,
                    "agent_id": [agent] * nf,
                    "sensor": ["LIDAR_TOP"] * nf,
                    "frame_idx": np.arange(nf),
                    "stamp_ns": t_start,
                    "t_start_ns": t_start,
                    "t_end_ns": t_start + 99_000_000,
                    "n_points": np.full(nf, npf),
                    "n_nan": np.zeros(nf, int),
                },
            ),
            agent,
        )
        fi = np.repeat(np.arange(nf), npf)
        rng = np.random.default_rng(ai)
        _write(
            lake,
            "lidar_points",
            columns_to_table(
                LidarPointRow,
                {
                    "clip_id": [CLIP] * len(fi),
                    "agent_id": [agent] * len(fi),
                    "sensor": pa.array(["LIDAR_TOP"] * len(fi)).dictionary_encode(),
                    "frame_idx": fi,
                    "t_ns": t_start[fi] + np.tile(np.arange(npf) * 2_000_000, nf),
                    "x": rng.normal(0, 10, len(fi)),
                    "y": rng.normal(0, 10, len(fi)),
                    "z": rng.normal(0, 1, len(fi)),
                    "intensity": rng.uniform(0, 1, len(fi)),
                    "ring": np.tile(np.arange(npf) % 32, nf),
                    "return_id": np.zeros(len(fi), int),
                },
            ),
            agent,
            row_group_by="frame_idx",
        )
        # cameras: real faces (astronaut, grace_hopper) and rendered plates
        rows = []
        for k in range(n_images):
            img, boxes = synth_scene(
                100 * ai + k, IMG_W, IMG_H, face_sizes=(40, 56), plate_widths=(60, 84)
            )
            key = lake.blob_key(CLIP, agent, "CAM_FRONT", k)
            ok, buf = cv2.imencode(".png", img)
            assert ok
            lake.write_blob("raw", key, buf.tobytes())
            truth[(agent, k)] = boxes
            rows.append(
                CameraFrameRow(
                    clip_id=CLIP,
                    agent_id=agent,
                    sensor="CAM_FRONT",
                    frame_idx=k,
                    stamp_ns=T_PPS + round(k * 1e9 / 30),
                    width=IMG_W,
                    height=IMG_H,
                    blob=key,
                    sha256="x",
                )
            )
        _write(lake, "camera_frames", rows_to_table(CameraFrameRow, rows), agent)
        _write(
            lake,
            "annotations",
            rows_to_table(
                AnnotationRow,
                [
                    AnnotationRow(
                        clip_id=CLIP,
                        agent_id=agent,
                        sensor="LIDAR_TOP",
                        frame_idx=0,
                        t_ns=int(t_start[0]),
                        instance_id="car-1",
                        category="vehicle.car",
                        cx=10.0,
                        cy=2.0,
                        cz=0.0,
                        w=1.9,
                        l=4.5,
                        h=1.5,
                        qw=1.0,
                        qx=0.0,
                        qy=0.0,
                        qz=0.0,
                        links=[],
                    )
                ],
            ),
            agent,
        )
    _write(
        lake,
        "qa_checks",
        rows_to_table(
            QaCheckRow,
            [
                QaCheckRow(
                    clip_id=CLIP,
                    check="pps_phase",
                    passed=True,
                    severity="error",
                    value=0.0,
                    threshold=1e6,
                    detail=f"on the PPS grid [+0.000 s] (abs {T_PPS}..{T_PPS + 9 * 10**8} ns)",
                )
            ],
        ),
    )
    return truth
