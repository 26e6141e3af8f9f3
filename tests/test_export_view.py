"""``v2xlake view``: a picture of one cooperative sample and one MCAP with every agent."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.export_fixtures import build_clean_clip
from v2xlake.storage.lake import Lake


@pytest.fixture(scope="module")
def lake(tmp_path_factory: pytest.TempPathFactory) -> Lake:
    lk = Lake(tmp_path_factory.mktemp("view") / "lake")
    build_clean_clip(lk, "clip-v", seconds=0.6, n_ground=2000)
    return lk


def test_view_cli_writes_png_and_mcap(lake: Lake, tmp_path: Path) -> None:
    from mcap.reader import make_reader

    from v2xlake.flows.cli import main

    assert main(["view", "clip-v", "--lake", lake.uri, "--out", str(tmp_path)]) == 0
    img = cv2.imread(str(tmp_path / "clip-v.png"))
    assert img is not None and img.shape[1] > img.shape[0] > 500
    # both agents' points are drawn in their colours (#e4572e red, #17bebb black; BGR)
    for bgr in ((46, 87, 228), (187, 190, 23)):
        near = np.abs(img.astype(int) - np.array(bgr)).sum(2) < 60
        assert near.sum() > 200, bgr
    mcap = next((tmp_path / "clip-v_all").glob("*.mcap"))
    with open(mcap, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    topics = {c.topic for c in summary.channels.values()}
    assert {"/red/lidar/points", "/black/lidar/points", "/red/boxes", "/black/boxes", "/tf",
            "/tf_static", "/red/camera/CAM_FRONT/image/compressed",
            "/black/camera/CAM_FRONT/image/compressed"} <= topics
    assert main(["view", "no-such", "--lake", lake.uri, "--out", str(tmp_path / "x")]) == 2
    assert main(["view", "../up", "--lake", lake.uri, "--out", str(tmp_path / "x")]) == 2
