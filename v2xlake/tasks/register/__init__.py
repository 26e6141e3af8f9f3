"""The register stage: cross-agent LiDAR transforms per frame pair (main paper eq. 1a from the
poses, refined by GICP as in eq. 1b), fused by a clip-level solve, and refined extrinsics.

- ``config.py``: its parameters (nested sections: gicp, quality, static, odometry, solve,
  calibration, redeskew, intra), pydantic only.
- ``stage.py``: the only module that touches the lake: reads the clip's agents, poses,
  extrinsics, deskewed scans (one frame at a time) and annotations, writes
  ``registrations``, ``calibration_refined`` and the figures, defines the ``REGISTER``
  Stage object, and the plots and ``v2xlake calibration`` rows read from stored tables.

The numeric core, on arrays and records:

- ``scans.py``: one agent's scans (``AgentScans``, built by ``stage.py``), re-deskewing with
  another extrinsic, and the static scene of each scan (``StaticScans``).
- ``voxel.py``: voxel downsampling (with each voxel's capture time).
- ``static.py``: what is removed before registration (annotated boxes, the other agents'
  bodies, moving points) and the LiDAR's height over the ground.
- ``backends.py``: GICP backends (small_gicp, Open3D, and the sparse one of ``sparse.py``)
  behind one protocol; ``covisible.py``: the part of a scan the other LiDAR sees from the
  same side, and the k-NN surface kernel both use.
- ``core.py``: eq. 1a (the initial transform) and one pair's refinement with its quality gate.
- ``solve.py``: the clip-level solve (cross-agent measurements, odometry, priors, robust
  weights, leave-one-out test) and the extrinsic corrections.
- ``intra.py``: one agent's secondary LiDAR registered to its primary (search, GICP,
  pooling); ``intra_stage.py``: that refinement over an agent's scans as the stage runs it,
  as ``calibration_refined`` rows; ``intra_data.py``: readers of the real lidar2lidar
  recordings' calibration and point files (benchmarks and tests).
- ``calibration.py``: the text of ``v2xlake calibration`` (published vs refined, per frame).
- ``bev.py`` and ``timeline.py``: the bird's-eye view of one frame (Fig. 5) and the clip's
  registration over time, as PNG (bytes, or a file the caller names), drawn by
  ``raster.py``: a small raster plotter (points counted into pixels, OpenCV lines, FreeType
  text), because matplotlib cost as much as registering a 3 s clip.
"""

from __future__ import annotations

from v2xlake.schemas.stage import StageDeclaration, tables

# what the registry reads without importing the stage (schemas/registry.py)
DECLARATION = StageDeclaration(
    name="register",
    owns=tables("clean", "registrations", "calibration_refined"))
