"""Camera ingest encodes frames on a thread pool: rows stay in frame order, every blob holds
exactly its own frame, and a frame that cannot be decoded still fails the clip by name."""

from __future__ import annotations

import hashlib
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from tests.fixtures.minibag import T0
from v2xlake.schemas.errors import ClipError
from v2xlake.storage.lake import Lake
from v2xlake.tasks.ingest import run_ingest
from v2xlake.tasks.ingest.stage import PNG_WORKERS

W, H = 32, 24
PERIOD = 33_333_333


def frame(i: int) -> np.ndarray:
    """Frame ``i`` (RGB): noise seeded by ``i``, so each frame is recognisable."""
    return np.random.default_rng(i).integers(0, 256, (H, W, 3), dtype=np.uint8)


def camera(name: str, topic: str, msg_type: str) -> dict[str, object]:
    return {"name": name, "modality": "camera", "topic": topic, "msg_type": msg_type,
            "rate_hz": 30,
            "extrinsic": {"translation": [1.5, 0, 1.5], "rotation": [0.5, -0.5, 0.5, -0.5]},
            "intrinsics": {"width": W, "height": H, "fx": 30.0, "fy": 30.0, "cx": W / 2,
                           "cy": H / 2}}


def write_clip(d: Path, frames: int, storage: str, corrupt_jpeg_at: int | None = None) -> Path:
    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    d.mkdir()
    with Writer(d / "red", version=8, storage_plugin=plugin) as w:
        raw = w.add_connection("/cam_a/image", "sensor_msgs/msg/Image", typestore=ts)
        jpg = w.add_connection("/cam_b/image", "sensor_msgs/msg/CompressedImage", typestore=ts)
        for i in range(frames):
            t = T0 + i * PERIOD
            header = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](
                sec=t // 10**9, nanosec=t % 10**9), frame_id="cam")
            img = frame(i)
            w.write(raw, t, ts.serialize_cdr(T["sensor_msgs/msg/Image"](
                header=header, height=H, width=W, encoding="rgb8", is_bigendian=0, step=3 * W,
                data=img.reshape(-1)), "sensor_msgs/msg/Image"))
            data = cv2.imencode(".jpg", img)[1].reshape(-1)
            if i == corrupt_jpeg_at:
                data = np.frombuffer(b"not a jpeg at all", np.uint8)
            w.write(jpg, t, ts.serialize_cdr(T["sensor_msgs/msg/CompressedImage"](
                header=header, format="jpeg", data=data), "sensor_msgs/msg/CompressedImage"))
    (d / "clip.yaml").write_text(yaml.safe_dump({
        "clip_id": "cams", "location": "test", "road_type": "local", "weather": "clear",
        "lighting": "day", "agents": [{
            "agent_id": "red", "kind": "vehicle", "role": "reference", "bag": "red",
            "tf_static_topic": None, "sensors": [
                camera("CAM_A", "/cam_a/image", "sensor_msgs/msg/Image"),
                camera("CAM_B", "/cam_b/image", "sensor_msgs/msg/CompressedImage")]}]}))
    return d


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_each_blob_holds_its_own_frame(tmp_path: Path, storage: str) -> None:
    frames = 6 * PNG_WORKERS + 3  # more frames than the pool keeps in flight
    clip = write_clip(tmp_path / "clip", frames, storage)
    lake = Lake(tmp_path / "lake")
    rep = run_ingest(lake, clip)
    assert rep.metrics["camera_frames"] == 2 * frames
    rows = lake.read_table("raw", "camera_frames", clip_id="cams").to_pylist()
    for name in ("CAM_A", "CAM_B"):
        mine = [r for r in rows if r["sensor"] == name]
        assert [r["frame_idx"] for r in mine] == list(range(frames))
        assert [r["stamp_ns"] for r in mine] == [T0 + i * PERIOD for i in range(frames)]
    for r in rows:
        png = lake.read_blob("raw", r["blob"])
        assert hashlib.sha256(png).hexdigest() == r["sha256"]
        back = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
        assert back is not None and back.shape == (H, W, 3)
        if r["sensor"] == "CAM_A":  # raw Image: lossless, RGB in the bag, BGR in the PNG
            assert np.array_equal(back[..., ::-1], frame(r["frame_idx"]))
        else:  # JPEG: the decoded JPEG pixels, still closest to their own frame
            err = [np.abs(back[..., ::-1].astype(int) - frame(i)).mean() for i in range(frames)]
            assert int(np.argmin(err)) == r["frame_idx"]


def test_undecodable_frame_names_camera_frame_and_topic(tmp_path: Path) -> None:
    clip = write_clip(tmp_path / "clip", 12, "mcap", corrupt_jpeg_at=7)
    lake = Lake(tmp_path / "lake")
    with pytest.raises(ClipError) as e:
        run_ingest(lake, clip)
    assert e.value.topic == "/cam_b/image" and e.value.agent_id == "red"
    assert "camera CAM_B frame 7" in str(e.value)
    assert not [f for f in lake.list_files(lake.path("raw")) if "cams" in f]
