"""``v2xlake.collate.collate_fn``: CoopDataset items (clouds of different sizes, agents and
boxes per sample) into one batch; in a real torch DataLoader when torch is installed."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

import v2xlake
from tests.export_fixtures import build_clean_clip
from v2xlake.collate import collate_fn
from v2xlake.storage.lake import Lake

CLIP = "clip-collate"


@pytest.fixture(scope="module")
def lake_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("collate") / "lake"
    build_clean_clip(Lake(root), CLIP, seconds=1.0, n_ground=800)
    return root


def _check(batch: dict, items: list[dict]) -> None:
    pc = np.asarray(batch["points_cat"])
    assert pc.shape == (sum(len(p) for it in items for p in it["points"].values()), 6)
    for b, it in enumerate(items):
        for a, agent in enumerate(it["agents"]):
            rows = pc[(pc[:, 0] == b) & (pc[:, 1] == a)][:, 2:]
            assert np.array_equal(rows, it["points"][agent])
            assert np.array_equal(np.asarray(batch["points"][b][agent]), it["points"][agent])
    bc = batch["boxes_cat"]
    n_boxes = sum(len(bx["center"]) for it in items for bx in it["boxes"].values())
    assert len(bc["category"]) == n_boxes and np.asarray(bc["center"]).shape == (n_boxes, 3)
    assert np.asarray(bc["batch_idx"]).max() == len(items) - 1
    assert list(np.asarray(batch["frame_idx"])) == [it["frame_idx"] for it in items]
    assert batch["clip_id"] == [CLIP] * len(items) and batch["agents"][0][0] == "red"


def test_collate_numpy(lake_dir: Path) -> None:
    ds = v2xlake.CoopDataset(lake_dir, stride=2, transform=lambda it: {**it, "n": 1})
    items = [ds[0], ds[1], ds[2]]
    sizes = {len(p) for it in items for p in it["points"].values()}
    assert len(sizes) > 1  # clouds differ in size: what the default collate cannot stack
    batch = collate_fn(items, to_tensor=False)
    _check(batch, items)
    assert isinstance(batch["points_cat"], np.ndarray)
    assert list(batch["n"]) == [1, 1, 1]  # a transform's key, stacked
    assert ds.collate_fn is collate_fn
    with pytest.raises(ValueError, match="empty"):
        collate_fn([])


def test_collate_in_a_torch_dataloader(lake_dir: Path) -> None:
    torch = pytest.importorskip(
        "torch", reason="torch is not installed (not a dependency: pip install torch)")
    from torch.utils.data import DataLoader, default_collate

    ds = v2xlake.CoopDataset(lake_dir, stride=2)
    items = [ds[0], ds[1]]
    with pytest.raises(RuntimeError):  # what users hit without a collate_fn
        default_collate(items)
    dl = DataLoader(ds, batch_size=2, num_workers=1 if os.name == "posix" else 0,
                    collate_fn=ds.collate_fn)
    batches = list(dl)
    assert sum(len(b["clip_id"]) for b in batches) == len(ds)
    first = batches[0]
    assert isinstance(first["points_cat"], torch.Tensor)
    assert first["points_cat"].dtype == torch.float32 and first["points_cat"].shape[1] == 6
    assert isinstance(first["T"][0]["red"], torch.Tensor)
    _check({**first, "points_cat": first["points_cat"].numpy()}, items)
