"""Far walkers under a sparse LiDAR, for clips guided by LiDAR clusters only.

The simulated seed-0 clip lost a face 48 m ahead of one car's narrow camera in three
frames: the other car's LiDAR, 32-35 m from the walker, put 4 returns on it (two rings of two
columns) in two of five sweeps and none in the others, alone in its 2 m ground cell. Three
things kept it from a head region: its lower ring was taken as the ground (so 2 returns
were left: no object), the rings above its top return had passed over its head (a box of its
returns puts the head region under the face), and the camera frames nearest the empty sweep
were guided by that sweep alone. Pure geometry, no images.
"""

from __future__ import annotations

import numpy as np
import pyarrow as pa

from v2xlake.tasks.anonymize.clusters import ClusterConfig, cluster_boxes, yaw_quat
from v2xlake.tasks.anonymize.context import assemble_guide
from v2xlake.tasks.anonymize.guide import GuideConfig, WorldBoxes
from v2xlake.tasks.interpolate import PoseTrack

# a walker 32 m away: two columns 0.55 m apart, rings at 0.45 and 1.13 m above the road
WALKER = np.array([(-32.0, y, z) for y in (8.0, 8.55) for z in (0.45, 1.13)])


def _road_without(centre: tuple[float, float], half_m: float) -> np.ndarray:
    """A flat road (z 0) sampled every 0.5 m, with no return within ``half_m`` of ``centre``
    along either axis (the road there hidden from the LiDAR)."""
    g = np.mgrid[-50:10:0.5, -10:20:0.5].reshape(2, -1).T
    hole = (np.abs(g[:, 0] - centre[0]) < half_m) & (np.abs(g[:, 1] - centre[1]) < half_m)
    g = g[~hole]
    return np.column_stack([g, np.zeros(len(g))])


def _people(cfg: ClusterConfig) -> np.ndarray:
    """Heights of the person boxes on the walker."""
    pts = np.vstack([_road_without((-31.0, 9.0), 3.2), WALKER])
    c, s, _yaw, cat = cluster_boxes(pts, cfg)
    near = np.hypot(c[:, 0] + 32.0, c[:, 1] - 8.27) < 1.0
    return np.sort(s[near & (cat == "Pedestrian"), 2])


def test_a_lone_far_walker_is_a_person_with_room_for_its_head() -> None:
    """The 2 m cell of the walker and the eight around it hold no road: its ground is the
    lower quartile of the cells within ``ground_isolated_m``, not its own lower ring. Its
    box of returns is 1.13 m tall (head region 0.6-1.3 m, under a 1.7 m walker's face); a
    second box is one point spacing (0.55 m) taller, whose head region reaches the face."""
    heights = _people(ClusterConfig())
    assert len(heights) == 2
    assert abs(heights[0] - 1.13) < 0.05
    assert abs(heights[1] - 1.68) < 0.05
    assert len(_people(ClusterConfig(ground_isolated_m=0.0))) == 0
    assert len(_people(ClusterConfig(sparse_person_top_m=0.0))) == 1
    assert len(_people(ClusterConfig(sparse_person_top_m=1.1))) == 1  # its top: 1.13 m


def test_the_isolated_ground_leaves_a_walker_on_seen_road_alone() -> None:
    """With road returns around it (the neighbour cells' median already the ground), the
    walker is the same person whether or not isolated cells are lowered."""
    pts = np.vstack([_road_without((-31.0, 9.0), 0.0), WALKER])
    for cfg in (ClusterConfig(), ClusterConfig(ground_isolated_m=0.0)):
        c, s, _yaw, cat = cluster_boxes(pts, cfg)
        near = np.hypot(c[:, 0] + 32.0, c[:, 1] - 8.27) < 1.0
        assert abs(s[near & (cat == "Pedestrian"), 2].min() - 1.13) < 0.05


def _scans() -> WorldBoxes:
    """Two scans 100 ms apart: a walker 20 m away, a walker 5 m away and a car in the first,
    the car alone in the second (the walkers got no return there)."""
    t = np.array([0, 0, 0, 100_000_000], np.int64)
    centre = np.array([[20.0, 3.0, 0.85], [5.0, 1.0, 0.85], [15.0, -2.0, 0.75],
                       [16.5, -2.0, 0.75]])
    size = np.array([[0.5, 0.5, 1.7], [0.5, 0.5, 1.7], [1.8, 4.5, 1.5], [1.8, 4.5, 1.5]])
    return WorldBoxes(t, centre, size, yaw_quat(np.zeros(4)), np.zeros((4, 3)),
                      np.array(["Pedestrian", "Pedestrian", "Car", "Car"]),
                      np.array(["lidar:a:L:0:0", "lidar:a:L:0:1", "lidar:a:L:0:2",
                                "lidar:a:L:1:0"]))


def test_far_person_boxes_of_neighbouring_scans_guide_an_image() -> None:
    """An image 90 ms after the first scan (the second one nearest) is guided by the second
    scan's boxes and by the first scan's far walker (20 m from the LiDAR), not by its near
    walker (5 m: returns in every sweep) nor its car (2 m away by then); with
    ``person_hold_ms`` 0 by the nearest scan alone; a scan beyond the hold is not used."""
    empty = pa.table({"t_ns": pa.array([], pa.int64())})
    track = PoseTrack.create(np.array([0, 200_000_000]), np.zeros((2, 3)),
                             np.tile([1.0, 0.0, 0.0, 0.0], (2, 1)))

    def at(hold_ns: int, t_ns: int) -> list[str]:
        cfg = GuideConfig(person_hold_ns=hold_ns)
        g = assemble_guide(0, {"a": track}, {}, {}, empty, pa.table({}), cfg, {"a": _scans()})
        return sorted(g._at(g.boxes["a"], t_ns, "a").instance.tolist())

    assert at(150_000_000, 90_000_000) == ["lidar:a:L:0:0", "lidar:a:L:1:0"]
    assert at(0, 90_000_000) == ["lidar:a:L:1:0"]
    assert at(150_000_000, 160_000_000) == ["lidar:a:L:1:0"]


def test_a_walker_the_nearest_scan_sees_again_is_not_held() -> None:
    """When the nearest scan has a person within ``person_hold_gap_m`` of a held one (the
    same walker, 0.15 m on), the older box adds nothing and is not held."""
    b = _scans()
    again = WorldBoxes(np.array([100_000_000], np.int64), np.array([[20.15, 3.0, 0.85]]),
                       np.array([[0.5, 0.5, 1.7]]), yaw_quat(np.zeros(1)), np.zeros((1, 3)),
                       np.array(["Pedestrian"]), np.array(["lidar:a:L:1:1"]))
    track = PoseTrack.create(np.array([0, 200_000_000]), np.zeros((2, 3)),
                             np.tile([1.0, 0.0, 0.0, 0.0], (2, 1)))
    empty = pa.table({"t_ns": pa.array([], pa.int64())})
    g = assemble_guide(0, {"a": track}, {}, {}, empty, pa.table({}), GuideConfig(),
                       {"a": WorldBoxes.concat([b, again])})
    assert sorted(g._at(g.boxes["a"], 90_000_000, "a").instance.tolist()) == [
        "lidar:a:L:1:0", "lidar:a:L:1:1"]
