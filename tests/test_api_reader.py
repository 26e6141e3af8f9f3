"""The one clean-zone reader (storage/reader.py): typed records of a clip, deskew's reference
time joined from its own table, points streamed per frame."""

from __future__ import annotations

import numpy as np
import pytest

from tests.export_fixtures import T0_NS, build_clean_clip
from v2xlake.storage.lake import Lake
from v2xlake.storage.reader import (
    NOT_DESKEWED,
    CameraCalib,
    available_frames,
    read_clip,
    read_point_frame,
)


@pytest.fixture(scope="module")
def lake(tmp_path_factory: pytest.TempPathFactory) -> Lake:
    lk = Lake(tmp_path_factory.mktemp("reader") / "lake")
    build_clean_clip(lk, "clip-r", seconds=0.5, n_ground=400, skip_deskewed_frames=(2,),
                     skip_deskewed_agent="black")
    return lk


def test_records_join_deskew_reference(lake: Lake) -> None:
    rec = read_clip(lake, "clip-r")
    assert list(rec.agents) == ["red", "black"]  # reference agent first
    red, black = rec.agents["red"], rec.agents["black"]
    lf = red.lidar["LIDAR_TOP"]
    assert lf.frame_idx.tolist() == [0, 1, 2, 3, 4]
    assert np.array_equal(lf.ref_ns, lf.t_start_ns) and lf.deskewed.all()
    bl = black.lidar["LIDAR_TOP"]
    assert bl.ref_ns[2] == NOT_DESKEWED and bl.deskewed.sum() == 4
    assert bl.points_t_ns[2] == bl.t_start_ns[2]  # a frame without deskewed points
    assert available_frames(lake, "clip-r", "black") == {0, 1, 3, 4}
    cam = red.cameras_calib()["CAM_FRONT"]
    assert isinstance(cam, CameraCalib) and cam.K[0, 0] == 160.0
    assert np.allclose(red.sensors["LIDAR_TOP"].T_ego_sensor[:3, 3], (0.6, 0.0, 1.8))
    assert red.pose_samples.t_ns[0] < T0_NS < red.pose_samples.t_ns[-1]
    assert red.annotations.num_rows and set(red.annotations["agent_id"].to_pylist()) == {"red"}
    # num_lidar_pts is annotate's count, not the delivered file's (null there)
    assert all(n is not None for n in red.annotations["num_lidar_pts"].to_pylist())


def test_point_frame_by_index(lake: Lake) -> None:
    fr = read_point_frame(lake, "clip-r", "red", 3)
    assert fr is not None and fr.frame_idx == 3 and fr.xyz.dtype == np.float32
    assert len(fr.xyz) == len(fr.t_ns) == len(fr.intensity) == len(fr.ring) > 100
    assert read_point_frame(lake, "clip-r", "black", 2) is None  # deskew left it out
