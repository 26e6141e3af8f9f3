"""A short LiDAR cluster is searched in both orientations (it may be a car seen end-on);
where another box of the same object is car-long, the orientation off its axis is dropped
(``clusters.off_axis_copies``, ``clusters.orient_by_object_ms``)."""

from __future__ import annotations

import numpy as np

from v2xlake.tasks.anonymize.clusters import off_axis_copies

MS = 1_000_000


def _boxes(ref_obj: int, ref_dt_ms: float, ref_len: float = 4.5):
    """Agent a's end-on car at (10, 0): its rear face (1.8 m along y, 0.5 m deep) as a box
    with its length along y (yaw 90°) and the copy along x (yaw 0); agent b's box of object
    ``ref_obj`` there, ``ref_len`` long along x (the car's axis), ``ref_dt_ms`` later."""
    t = np.array([0, 0, int(ref_dt_ms * MS)], np.int64)
    centre = np.array([[10.0, 0.0, 0.8], [10.0, 0.0, 0.8], [11.5, 0.0, 0.8]])
    size = np.array([[0.5, 1.8, 1.5], [1.8, 0.5, 1.5], [1.8, ref_len, 1.5]])
    yaw = np.array([np.pi / 2, np.pi, 0.0])  # the copy: yaw + 90°
    cat = np.array(["Car", "Car", "Car"])
    obj = np.array([7, 7, ref_obj])
    lidar = np.array(["lidar:a:top", "lidar:a:top", "lidar:b:top"])
    return t, centre, size, yaw, cat, obj, lidar


def test_the_copy_off_the_objects_axis_is_dropped() -> None:
    t, c, s, y, cat, obj, lid = _boxes(ref_obj=7, ref_dt_ms=50)
    drop = off_axis_copies(t, c, s, y, cat, obj, 200 * MS, 3.0, lid)
    # the box along y (its faces at y = +-0.9: the car's sides) goes, the one along x stays
    assert drop.tolist() == [True, False, False]


def test_both_orientations_stay_without_a_long_box_of_the_object() -> None:
    for args, window_ms in (((8, 50), 200),  # another object's box
                            ((7, 500), 200),  # too far in time
                            ((7, 50, 2.5), 200)):  # not car-long: its axis is unknown too
        t, c, s, y, cat, obj, lid = _boxes(*args)
        drop = off_axis_copies(t, c, s, y, cat, obj, window_ms * MS, 3.0, lid)
        assert not drop.any()


def test_the_settings_reach_the_provenance() -> None:
    from v2xlake.tasks.anonymize.config import AnonymizeConfig

    p = AnonymizeConfig().provenance("v")
    assert "clusters.orient_by_object_ms=500" in p and "regions.plate_pack_fit=True" in p
    for upd in ({"clusters": {"orient_by_object_ms": 0}}, {"regions": {"plate_pack_fit": False}}):
        assert AnonymizeConfig(**upd).provenance("v") != p
