"""``collate_fn`` for :class:`v2xlake.CoopDataset` in a PyTorch ``DataLoader``.

PyTorch's default collate stacks arrays of equal shape; point clouds and box lists differ in
size between samples and agents (and agents differ between samples), so it fails on the
first batch. This one keeps what varies as per-sample lists and adds the layout most LiDAR
detectors take (OpenPCDet, MMDetection3D): every point of the batch in one array with its
sample and agent index in front::

    from torch.utils.data import DataLoader
    from v2xlake.collate import collate_fn
    loader = DataLoader(CoopDataset(lake), batch_size=4, collate_fn=collate_fn, num_workers=2)
    batch = next(iter(loader))
    batch["points_cat"]      # (sum N, 6): sample index, agent index, x, y, z, intensity
    batch["points"][0]["red"]  # sample 0, agent red: (N, 4)

A batch is a dict: ``clip_id``, ``agents``, ``T_source``, ``T_source_reason`` (lists, one
entry per sample); ``frame_idx`` and ``t_ns`` (int64, (B,)); ``points``, ``boxes``, ``T`` (and
``images``) as lists of the samples' own dicts, their arrays as tensors; ``points_cat`` as
above, the agent index being the agent's position in that sample's ``agents`` (0: the
reference agent); ``boxes_cat``: dict of arrays over every box of the batch, with
``batch_idx`` and ``agent_idx``, ``category`` a list of strings. Anything else a
``transform`` added is collated per key: arrays of one shape are stacked, the rest kept as
lists.

Tensors when torch is importable (it is not a dependency of v2xlake: nothing here imports it
unless it is installed), NumPy arrays otherwise (``to_tensor=False`` forces NumPy).
"""

from __future__ import annotations

import importlib.util
from collections.abc import Sequence
from typing import Any

import numpy as np

__all__ = ["collate_fn"]

KNOWN = ("clip_id", "frame_idx", "t_ns", "agents", "points", "boxes", "T", "T_source",
         "T_source_reason", "images")
BOX_ARRAYS = ("instance_id", "center", "size", "quat_wxyz", "velocity", "num_lidar_pts")


def _torch_available() -> bool:
    return importlib.util.find_spec("torch") is not None


def _convert(x: Any, tensor: bool) -> Any:
    """NumPy arrays (nested in dicts and lists) to tensors; everything else unchanged."""
    if isinstance(x, np.ndarray):
        if not tensor or x.dtype.kind not in "biuf":  # strings / objects stay NumPy
            return x
        import torch

        return torch.from_numpy(np.ascontiguousarray(x))
    if isinstance(x, dict):
        return {k: _convert(v, tensor) for k, v in x.items()}
    if isinstance(x, list):
        return [_convert(v, tensor) for v in x]
    return x


def _cat_points(batch: Sequence[dict[str, Any]]) -> np.ndarray:
    parts = []
    for b, item in enumerate(batch):
        for a, agent in enumerate(item["agents"]):
            pts = np.asarray(item["points"].get(agent, np.zeros((0, 4), np.float32)),
                             np.float32).reshape(-1, 4)
            idx = np.empty((len(pts), 2), np.float32)
            idx[:, 0], idx[:, 1] = b, a
            parts.append(np.concatenate([idx, pts], 1))
    return np.concatenate(parts, 0) if parts else np.zeros((0, 6), np.float32)


def _cat_boxes(batch: Sequence[dict[str, Any]]) -> dict[str, Any]:
    cols: dict[str, list[np.ndarray]] = {k: [] for k in (*BOX_ARRAYS, "batch_idx", "agent_idx")}
    category: list[str] = []
    for b, item in enumerate(batch):
        for a, agent in enumerate(item["agents"]):
            boxes = item["boxes"].get(agent)
            if not boxes:
                continue
            n = len(boxes["center"])
            for k in BOX_ARRAYS:
                cols[k].append(np.asarray(boxes[k]))
            cols["batch_idx"].append(np.full(n, b, np.int64))
            cols["agent_idx"].append(np.full(n, a, np.int64))
            category.extend(str(c) for c in boxes["category"])
    out: dict[str, Any] = {}
    for k, parts in cols.items():
        out[k] = (np.concatenate(parts, 0) if parts
                  else np.zeros((0, 3) if k in ("center", "size", "velocity")
                                else (0, 4) if k == "quat_wxyz" else (0,),
                                np.float32 if k in ("center", "size", "velocity", "quat_wxyz")
                                else np.int64))
    out["category"] = category
    return out


def _stack_or_list(values: list[Any]) -> Any:
    arrays = [np.asarray(v) for v in values] if all(
        isinstance(v, np.ndarray | int | float | np.number) for v in values) else None
    if arrays and len({(a.shape, a.dtype) for a in arrays}) == 1:
        return np.stack(arrays)
    return values


def collate_fn(batch: Sequence[dict[str, Any]], *, to_tensor: bool | None = None
               ) -> dict[str, Any]:
    """Collate :class:`~v2xlake.CoopDataset` items (see the module docstring)."""
    if not batch:
        raise ValueError("collate_fn: empty batch")
    tensor = _torch_available() if to_tensor is None else to_tensor
    out: dict[str, Any] = {
        "clip_id": [it["clip_id"] for it in batch],
        "frame_idx": np.asarray([it["frame_idx"] for it in batch], np.int64),
        "t_ns": np.asarray([it["t_ns"] for it in batch], np.int64),
        "agents": [list(it["agents"]) for it in batch],
        "points": [dict(it["points"]) for it in batch],
        "boxes": [dict(it["boxes"]) for it in batch],
        "T": [dict(it["T"]) for it in batch],
        "T_source": [dict(it.get("T_source", {})) for it in batch],
        "T_source_reason": [dict(it.get("T_source_reason", {})) for it in batch],
        "points_cat": _cat_points(batch),
        "boxes_cat": _cat_boxes(batch),
    }
    if any("images" in it for it in batch):
        out["images"] = [it.get("images", {}) for it in batch]
    for key in batch[0]:
        if key not in KNOWN and key not in out:  # what a transform added
            out[key] = _stack_or_list([it.get(key) for it in batch])
    return {k: (v if k in ("clip_id", "agents", "T_source", "T_source_reason")
                else _convert(v, tensor)) for k, v in out.items()}
