"""Consistency of a clip's boxes, on arrays: boxes moved into the world frame, distances
between two agents' boxes of one instance, and link checks (no lake, no files)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from v2xlake.tasks.geometry import transform_boxes


@dataclass(frozen=True)
class WorldBoxes:
    center: np.ndarray  # (M, 3)
    quat: np.ndarray  # (M, 4)
    velocity: np.ndarray  # (M, 3), NaN where unknown


def world_boxes(T_world_l0: np.ndarray, center: np.ndarray, quat: np.ndarray,
                velocity: np.ndarray) -> WorldBoxes:
    """Boxes given in L0 (one ``T_world_L0`` (M, 4, 4) per box) -> world frame."""
    return WorldBoxes(*transform_boxes(T_world_l0, center, quat, velocity))


def cross_agent_distances(
    instance_id: np.ndarray, agent: np.ndarray, t_ns: np.ndarray, center: np.ndarray,
    velocity: np.ndarray, max_dt_ns: int,
) -> np.ndarray:
    """Distances between two agents' boxes of the same instance (world frame).

    For each box of each instance, the other agents' box of that instance nearest in time
    (within ``max_dt_ns``) is moved to the first box's time with its velocity (if known),
    and the centre distance taken. Each unordered pair is counted once.
    """
    out: list[float] = []
    for inst in np.unique(instance_id):
        rows = np.flatnonzero(instance_id == inst)
        agents = np.unique(agent[rows])
        if agents.size < 2:
            continue
        for ia, a in enumerate(agents):
            ra = rows[agent[rows] == a]
            for b in agents[ia + 1:]:
                rb = rows[agent[rows] == b]
                for r in ra:
                    dt = t_ns[rb] - t_ns[r]
                    k = int(np.argmin(np.abs(dt)))
                    if abs(int(dt[k])) > max_dt_ns:
                        continue
                    j = rb[k]
                    v = np.nan_to_num(velocity[j], nan=0.0)
                    moved = center[j] - v * (dt[k] * 1e-9)
                    out.append(float(np.linalg.norm(moved - center[r])))
    return np.asarray(out, dtype=np.float64)


def check_links(
    agent: np.ndarray, frame_idx: np.ndarray, instance_id: np.ndarray, links: list[list[str]],
    center: np.ndarray, length: np.ndarray, max_gap_m: float,
) -> tuple[list[str], list[str], int]:
    """(unknown-target messages, too-far messages, links whose target is not in that scan)."""
    known = set(instance_id.tolist())
    where: dict[tuple[str, int, str], int] = {
        (str(a), int(f), str(i)): r
        for r, (a, f, i) in enumerate(zip(agent, frame_idx, instance_id, strict=True))
    }
    unknown: list[str] = []
    far: list[str] = []
    n_absent = 0
    for r, lk in enumerate(links):
        for target in lk:
            if target not in known:
                unknown.append(f"{instance_id[r]} links to unknown instance {target}")
                continue
            j = where.get((str(agent[r]), int(frame_idx[r]), target))
            if j is None:
                n_absent += 1
                continue
            d = float(np.linalg.norm(center[r] - center[j]))
            limit = (length[r] + length[j]) / 2 + max_gap_m
            if d > limit:
                far.append(f"{instance_id[r]} -> {target} in {agent[r]} frame {frame_idx[r]}: "
                           f"{d:.2f} m apart (limit {limit:.2f} m)")
    return unknown, far, n_absent

