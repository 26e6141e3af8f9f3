"""Schemas reject bad values with messages that name the field."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest
from pydantic import ValidationError
from scipy.spatial.transform import Rotation

from v2xlake.schemas.annotation import AnnotationFile, Box3D, BoxAnnotation, ObjectClass
from v2xlake.schemas.arrow import arrow_schema, columns_to_table, rows_to_table
from v2xlake.schemas.calibration import CameraIntrinsics, DistortionModel
from v2xlake.schemas.clip import ClipConfig
from v2xlake.schemas.geometry import Transform, matrix_to_quat, quat_to_matrix
from v2xlake.schemas.nuscenes import NUSCENES_TABLES, Sample
from v2xlake.schemas.tables import LAKE_TABLES, LidarPointRow, QaCheckRow


def _clip_dict() -> dict:
    lidar = {
        "name": "LIDAR_TOP", "modality": "lidar", "topic": "/red/lidar/points",
        "msg_type": "sensor_msgs/msg/PointCloud2",
        "fields": {"time": {"field": "timestamp", "unit": "s", "reference": "absolute"}},
    }
    return {
        "clip_id": "c1", "location": "town", "road_type": "arterial", "weather": "clear",
        "lighting": "day",
        "agents": [
            {"agent_id": "red", "kind": "vehicle", "role": "reference", "bag": "red",
             "sensors": [lidar]},
            {"agent_id": "black", "kind": "vehicle", "role": "cooperative", "bag": "black",
             "sensors": [lidar]},
        ],
    }


def test_transform_rejects_non_unit_quaternion_naming_field() -> None:
    with pytest.raises(ValidationError) as e:
        Transform(translation=[0, 0, 0], rotation=[1.0, 0.1, 0, 0])
    assert "rotation" in str(e.value) and "unit quaternion" in str(e.value)


def test_transform_rejects_non_orthonormal_and_reflection() -> None:
    m = np.eye(4)
    m[0, 1] = 0.05
    with pytest.raises(ValueError, match="orthonormal"):
        Transform.from_matrix(m)
    m = np.diag([1.0, 1.0, -1.0, 1.0])
    with pytest.raises(ValueError, match="reflection"):
        Transform.from_matrix(m)


def test_transform_round_trip_and_composition() -> None:
    rng = np.random.default_rng(0)
    for _ in range(20):
        r = Rotation.random(random_state=rng.integers(1 << 31)).as_matrix()
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = r, rng.normal(size=3)
        t = Transform.from_matrix(m)
        np.testing.assert_allclose(t.matrix(), m, atol=1e-12)
        inv = Transform.from_matrix(np.linalg.inv(m))
        np.testing.assert_allclose(t.matrix() @ inv.matrix(), np.eye(4), atol=1e-12)
    q = matrix_to_quat(quat_to_matrix(np.array([0.0, 0.0, 0.0, -1.0])))
    assert q[0] >= 0  # canonical sign


def test_intrinsics_validation() -> None:
    CameraIntrinsics(width=640, height=360, fx=500, fy=500, cx=320, cy=180,
                     distortion_model=DistortionModel.PLUMB_BOB, distortion=[0.1, 0, 0, 0, 0])
    with pytest.raises(ValidationError, match="principal point"):
        CameraIntrinsics(width=640, height=360, fx=500, fy=500, cx=900, cy=180)
    with pytest.raises(ValidationError, match="coefficients"):
        CameraIntrinsics(width=640, height=360, fx=500, fy=500, cx=320, cy=180,
                         distortion_model="plumb_bob", distortion=[0.1, 0.0])
    with pytest.raises(ValidationError, match="fx"):
        CameraIntrinsics(width=640, height=360, fx=-1, fy=500, cx=320, cy=180)


def test_clip_contract_enums_and_reference(tmp_path) -> None:
    cfg = ClipConfig.model_validate(_clip_dict())
    assert cfg.reference_agent.agent_id == "red"
    cfg.dump(tmp_path)
    assert ClipConfig.load(tmp_path) == cfg
    bad = _clip_dict()
    bad["weather"] = "sunny"
    with pytest.raises(ValidationError, match="weather"):
        ClipConfig.model_validate(bad)
    bad = _clip_dict()
    bad["agents"][1]["role"] = "reference"
    with pytest.raises(ValidationError, match="exactly one agent"):
        ClipConfig.model_validate(bad)
    bad = _clip_dict()
    del bad["agents"][0]["sensors"][0]["fields"]
    with pytest.raises(ValidationError, match="time field"):
        ClipConfig.model_validate(bad)


def test_annotations_taxonomy_and_links() -> None:
    box = Box3D(center=[1, 2, 0], size=[1.9, 4.5, 1.6], rotation=[1, 0, 0, 0])
    car = BoxAnnotation(agent_id="red", frame_idx=0, t_ns=0, instance_id="car-1",
                        category="Car", box=box, links=["trailer-1"])
    trailer = BoxAnnotation(agent_id="red", frame_idx=0, t_ns=0, instance_id="trailer-1",
                            category=ObjectClass.TRAILER, box=box)
    AnnotationFile(clip_id="c", annotations=[car, trailer])
    with pytest.raises(ValidationError, match="unknown instances"):
        AnnotationFile(clip_id="c", annotations=[car])
    with pytest.raises(ValidationError, match="category"):
        BoxAnnotation(agent_id="red", frame_idx=0, t_ns=0, instance_id="x", category="Tank",
                      box=box)
    with pytest.raises(ValidationError, match="positive"):
        Box3D(center=[0, 0, 0], size=[0, 1, 1], rotation=[1, 0, 0, 0])
    assert ObjectClass.BICYCLE.is_vru and not ObjectClass.BUS.is_vru


def test_arrow_schemas_derive_from_models() -> None:
    for model in [*LAKE_TABLES.values(), *NUSCENES_TABLES.values()]:
        assert len(arrow_schema(model)) == len(model.model_fields)
    s = arrow_schema(LidarPointRow)
    assert s.field("x").type == pa.float32() and s.field("ring").type == pa.uint16()
    assert s.field("t_ns").type == pa.int64()
    t = rows_to_table(QaCheckRow, [{"clip_id": "c", "check": "pps", "passed": True,
                                    "severity": "error", "detail": "ok"}])
    assert t.column("agent_id").null_count == 1
    with pytest.raises(KeyError, match="missing"):
        columns_to_table(LidarPointRow, {"x": np.zeros(2)})
    with pytest.raises(ValidationError):
        Sample(token="nothex", timestamp=0, prev="", next="", scene_token="0" * 32)
