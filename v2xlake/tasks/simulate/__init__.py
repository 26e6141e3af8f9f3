"""Realistic multi-agent recorder simulator: writes a clip folder (COMMON.md) from a seed.

Public API: :class:`SimConfig` (``SimConfig.preset(name, **overrides)``, name one of
``small``, ``street``, ``coop``, ``cats``), :func:`simulate` ``(out_dir, config) -> Path``,
:func:`load_truth` ``(clip_dir) -> SimTruth``. See the module docstrings for every convention:
``trajectory`` (time, world, body frames), ``rig`` (sensor frames, calibration errors),
``boulevard`` (the cooperative scenario of issue #21: a straight road, every vehicle on its own
profile), ``lidar`` (PPS phase lock, per-column time, dual return, intensity), ``camera``
(trigger times, rendering, 2D truth), ``ins`` (INS/IMU/GNSS error model), ``bagwrite``
(message layout, log-time latencies), ``truth`` (ground truth files).

Changes for consumers: (1) ``truth/boxes2d.parquet`` boxes now come from what is really drawn
(occluders erase faces / plates beneath them) and carry ``visible_fraction`` / ``occluded``
columns (``camera``); (2) INS / IMU / GNSS run past the last LiDAR sweep's end by 20 ms so every
scan, the last included, is bracketed by INS samples (``run``): 128 INS / 11 GNSS per 1 s clip.

Precision note: the PointCloud2 ``timestamp`` field is float64 absolute seconds (the contract);
at ~1.7e9 s its resolution is 2^-22 s = 238 ns, so ``round(timestamp * 1e9)`` may differ from
the exact column time by up to ~120 ns (2.4 um at 20 m/s). Geometry is cast at the exact
integer-ns column times.
"""

from v2xlake.tasks.simulate.config import SimConfig
from v2xlake.tasks.simulate.run import simulate
from v2xlake.tasks.simulate.truth import SimTruth, load_truth

__all__ = ["SimConfig", "SimTruth", "load_truth", "simulate"]
