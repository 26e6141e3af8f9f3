"""Parameters of the register stage, one section per part of the algorithm.

Each section is the object its numeric core takes: ``gicp`` the GICP backends
(:mod:`backends`), ``quality`` the per-frame accept test (:mod:`core`), ``static`` the
static-scene filter (:mod:`scans`), ``odometry`` the agents' own scan-to-scan GICP, ``solve``
the clip solve (:mod:`solve`), ``calibration`` when a refined extrinsic is usable,
``redeskew`` and ``intra`` (several LiDARs on one agent). Every parameter is written here
once, with its default and why it has that value.

Only pydantic is imported: ``v2xlake params show`` reads this module without the numeric code.
Parameter files of earlier versions used flat keys (``voxel_m``, ``prior_ext_m``,
``refined_require_all``...); ``RENAMED`` moves them into their sections with a warning.
"""

from __future__ import annotations

from typing import ClassVar, Literal

from pydantic import Field

from v2xlake.schemas.config import Section, StageConfig


class GicpSection(Section):
    """Generalized-ICP of one pair of scans (main paper eq. 1b)."""

    backend: Literal["small_gicp", "sparse", "open3d"] = Field(
        "sparse", description="GICP implementation: sparse (a spread sample of the source, "
        "surfaces computed only where correspondences land, more centroids where the sample "
        "finds too few: register/sparse.py), small_gicp (every point of both clouds) or "
        "open3d. On 239k-point scan pairs sparse takes 0.036 s per pair against 0.160 s for "
        "small_gicp (one core, same run); on the cooperative boulevard's variations neither "
        "accepted a frame outside 3 cm / 0.1 deg, and on consecutive real Ouster OS-1-128 "
        "and Velodyne VLP-16 scans the two agree within 3 mm / 0.02 deg")
    voxel_m: float = Field(
        0.3, gt=0, description="target (reference scan) voxel size. Coarse voxels bias the "
        "relative pose along a street: a voxel's centroid on poles, car bodies and wall "
        "edges depends on the side each agent saw it from. Measured on the cooperative "
        "boulevard (64 x 1024 scans): 0.6 / 1.0 m left the frames' GICP 2.2 cm off along "
        "the street (median) and 9 of 100 frames 3.1-3.3 cm off; 0.3 / 0.3 m 0.7 cm, none "
        "beyond 2.8 cm, at about 3x the GICP time")
    source_voxel_m: float = Field(
        0.3, gt=0, description="source (other scan) voxel size. 0.6 m is 35 % faster but "
        "its centroids are biased the same way: on the boulevard the median error grew from "
        "0.8 to 1.1-1.8 cm")
    max_range_m: float = Field(80.0, gt=0, description="points farther than this are "
                               "dropped (sparse, noisy, and cropping saves time)")
    num_neighbors: int = Field(10, ge=5, description="neighbours per covariance")
    far_pair_num_neighbors: int | None = Field(
        6, ge=5, description="neighbours per covariance of a far cross pair's surfaces "
        "(both scans; the two LiDARs farther apart than far_pair_beyond_m by the INS), "
        "computed a second time per scan where a far pair needs them (a reference scan can "
        "be the target of a near and a far pair); near pairs and odometry keep "
        "num_neighbors. None: num_neighbors for every pair. WHY: on the far agent's sparse "
        "rings 10 nearest 0.3 m centroids reach over several rings and bend over edges, "
        "leaning the normals and GICP's own minimum along the street (issue #21). Safety "
        "bar 2026-11-28 (48 clips + the hard street with and without annotations, None -> "
        "6): within 3653 -> 3783, accepted 2855 -> 3183, none outside 3 cm / 0.1 deg with "
        "either; the 36 far clip-pairs 2110 / 1359 -> 2240 / 1687 (50 m ahead 10 s 81 -> 94 "
        "of 100, seed 3 50 m behind 73 -> 91, the roadside unit 87 -> 100), the near clips "
        "identical; within lower on two roadside-unit pairs (3 s 22 -> 20, seed 2 10 s 70 "
        "-> 69); register CPU 137.7 -> 128.0 s. 6 for every pair instead accepted 4-5 wrong "
        "near frames, and 6 for points beyond 40 m 12")
    far_pair_beyond_m: float = Field(
        40.0, gt=0, description="the range between the two LiDARs (by the INS) beyond which "
        "a cross pair takes far_pair_num_neighbors: the far agent's column spacing (at 40 m "
        "a 1024-column LiDAR's columns are 0.25 m apart, most of a 0.3 m voxel), the range "
        "the solve's floor_range_m uses")
    far_pair_denser_side: Literal["off", "stationary", "far"] = Field(
        "stationary", description="sparse backend, which cross pairs take each spot's "
        "correspondences from the scan that sampled it more densely: 'stationary' a pair "
        "with a stationary agent (either side), 'far' also every far pair (the two LiDARs "
        "farther apart than far_pair_beyond_m), 'off' none. Which scan sampled a spot more "
        "densely is judged by which LiDAR is nearer (the same sensors: ring spacing grows "
        "with range). The source's "
        "sample points nearer the target LiDAR are matched into the target as usual; every "
        "target point nearer the source LiDAR is matched to its nearest source point (the "
        "same GICP term, both surfaces). WHY: far from its LiDAR a scan's rings are far "
        "apart; a dense point matched to the nearest centroid of a sparse ring lies up to "
        "half a ring spacing from it in the plane, and the sparse side's normal (its "
        "neighbours span several rings) leans, so GICP's own minimum moves along the street. "
        "The information a pair reports stays its forward correspondences' Hessian (the "
        "split cost's, with fewer points on the sparse side, cut what the solve accepted: "
        "far clips 1699 -> 1371 accepted with 'far'). Safety bar 2026-11-28 (48 clips + the "
        "hard street, 'off' -> 'stationary'): within 3809 -> 3835, accepted 3195 -> 3200, "
        "none outside 3 cm / 0.1 deg with either; roadside-unit pairs at 10 s 485 -> 500 of "
        "500 within (seed 2 93 -> 100, seed 5 92 -> 100, medians 0.14-1.14 -> 0.09-0.45 cm), "
        "at 3 s 139 -> 150 of 150; the clips without a roadside unit identical; within "
        "lower on none, accepted lower on four pairs whose 1-sigma sits at the 2.0 cm "
        "limit (seed 4's 3 s unit 7 -> 4, seed 2's black 97 -> 95); register CPU of the "
        "roadside-unit clips 23.6 s both. 'far' also moves the vehicles 50 m apart: within "
        "3853 but accepted 3168 (their GICP scatter grew, 0.85 -> 1.15 cm rms along the "
        "street on black 50 m behind's steady frames: the far half's forward pairs, dense "
        "but biased, also averaged noise away)")
    sample_cell_m: float | None = Field(
        0.9, gt=0, description="sparse backend: one source centroid (of the fine voxels) per "
        "cell of this size is aligned, with the surface of its full-resolution neighbourhood; "
        "None: every centroid (the same result as small_gicp). 0.6 m measured like 0.9 m on "
        "the boulevard at 1.3x the GICP time")
    sample_min_pairs: int = Field(
        3000, ge=0, description="sparse backend: when the sample finds fewer correspondences "
        "than this (little overlap: the other agent far away or around a corner), the pair "
        "is aligned again from the sample's result with more source centroids "
        "(sample_fallback). The sample's "
        "spread is what leaves a far pair short of constraints: 50 m behind, its 2,200 pairs "
        "left single frames 3-15 cm off where every centroid keeps them within 2 cm. 0: "
        "never")
    sample_fallback: Literal["every", "matched", "finer"] = Field(
        "every", description="sparse backend, what a pair whose sample found fewer than "
        "sample_min_pairs correspondences is aligned again with: 'every' every (co-visible) "
        "source centroid; 'matched' every centroid of the sample cells whose sample point "
        "found a correspondence (where the overlap is); 'finer' a spread sample with the cell "
        "shrunk by sqrt(found / sample_min_pairs). 'matched' cut the roadside unit's 3 s clip "
        "from 6.3 to 5.4 s of register CPU (50 m behind 3 s 3.2 -> 2.5 s) and on all 28 "
        "boulevard variations accepted as many frames or more, none outside 3 cm / 0.1 deg, "
        "but on the hard street without annotations (32-beam test clip, 1.0 m source voxels, "
        "where nearly every pair falls back) it accepted 93 instead of 104 of 120 frames; "
        "'finer' (4.3 s on the roadside unit) accepted 50 instead of 51 of the roadside "
        "unit's frames")
    covisible_target_rows: int = Field(
        500, ge=0, description="sparse backend with covisible: a cross pair's target falls "
        "back to its whole scan when less than max(quality.min_inliers, 30 %) of it is "
        "co-visible; that fraction is estimated on this many of the target's sample rows, "
        "evenly strided (binomial 1-sigma at most 2.2 % at 500). 0: on every sample row "
        "(3,000-4,000 on the boulevard, each a k-nearest-neighbour surface)")
    fallback_translation_eps_m: float = Field(
        1e-3, gt=0, description="sparse backend: the re-alignment of a short sample "
        "(sample_min_pairs) stops when its translation step is below this (and its rotation "
        "step below 0.1 deg), as every GICP here does at 1 mm. Far pairs slide along their "
        "weak direction in steps shrinking by a fifth per iteration (7, 6, 5 ... 1 mm); 300 of "
        "the 521 dense iterations on the roadside unit's 10 s clip are in passes of 12 or "
        "more. 3 mm: that clip's register CPU -9 %, but on the full bar (28 boulevard "
        "variations, hard street) black 50 m behind (10 s) had 93 instead of 99 of 100 "
        "frames within 3 cm / 0.1 deg (none accepted either way): not the default")
    dense_after_short_sample: bool = Field(
        False, description="sparse backend, sample_fallback 'every': a cross pair whose "
        "previous frame's sample found fewer than sample_min_pairs correspondences is aligned "
        "with every co-visible source centroid at once, from the warm start, without the "
        "sample pass first (whether its sample would have been short is read from that "
        "alignment's last search, so a pair goes back to the sample when the overlap "
        "grows). WHY: a far pair (a roadside unit 70 m away) is short in nearly every frame "
        "and its sample pass is then spent for nothing. Not the default: on the boulevard "
        "with black 50 m ahead (3 s) the median went 1.52 -> 2.14 cm and 17 -> 16 frames "
        "within 3 cm (the sample pass's result is the better start); the roadside unit's 3 s "
        "clip 13 -> 16 within, median 3.43 -> 2.93 cm")
    reference_max_range_m: float | None = Field(
        120.0, gt=0, description="the reference agent's scans (the target of every cross "
        "pair) keep their points to this range instead of max_range_m; None: max_range_m. "
        "WHY: a roadside unit 50-80 m away sees the street around and beyond itself, but cut "
        "at 80 m the reference's scan ends just past it, so the pair's position along the "
        "street rests on the in-plane terms of walls and road (the walls say nothing along "
        "it), which the reference's thinning points near its range cut pull toward the "
        "reference: GICP settled 2-15 cm short (median of the 50-80 m frames per side). Four "
        "10 s clips, median shortfall approaching / receding, cm: 4.0 / 15.0, 6.9 / 1.7, "
        "14.2 / 13.1, 3.8 / 15.1 -> at 120 m 3.8 / 0.0, 1.1 / 1.0, 0.2 / -0.3, 3.5 / 0.2 "
        "(100 m and 200 m the same); rsu within 3 cm / 0.1 deg 59 / 57 / 54 / 54 -> 87 / 69 / "
        "100 / 85 of 100, median 2.3-2.6 -> 0.4-1.5 cm, none accepted outside, accepted "
        "25 / 0 / 28 / 24 -> 27 / 0 / 37 / 27; the other vehicle's medians within 0.06 cm, "
        "seed 2's accepted 99 -> 98. The default since the safety bar (every --coop "
        "variation at 3 and 10 s and the hard street, against None): none accepted outside "
        "3 cm / 0.1 deg, within never lower (black 50 m ahead 0 -> 78 / 100 at 10 s, 17 -> "
        "30 / 30 at 3 s; 50 m behind 99 -> 100, median 1.71 -> 0.74 cm; the hard street 115 "
        "-> 120 and 112 -> 119 / 120), medians at most +0.05 cm, accepted +1 to +5 on eight "
        "clips and -1 on three (seed 2 10 s 97 -> 96, its roadside-unit clip's black 99 -> "
        "98, the 40 cm extrinsic 3 s 28 -> 27), register CPU the same or lower on most. "
        "None: every agent cut at max_range_m")
    reuse_last_search: bool = Field(
        True, description="sparse backend: a pair's quality figures (fitness, inlier RMSE) "
        "come from the nearest-neighbour search of GICP's last iteration, one update before "
        "its result (under 0.1 deg / 1 mm at convergence), instead of a search of their own "
        "(a fifth of a cross pair's nearest-neighbour searches); off: searched again at the "
        "result")
    max_correspondence_m: float = Field(1.0, gt=0)
    grid_cell_m: float = Field(
        1.6, gt=0, description="sparse backend: cell of the grid its nearest-neighbour "
        "searches use (register/voxel.py VoxelGrid). Speed only, the searches are exact at "
        "any size (of points at exactly one distance, perhaps another). At least "
        "max_correspondence_m (a nearest neighbour within it is then always in the query's "
        "cell or the 26 around it). 1.6 m, as knn_grid_cell_m, so that a scan has one grid: "
        "with the occupancy bitmap a cell looked up costs more than a few more points "
        "scanned; the GICP searches of the register stage, replayed (seed 2's roadside unit "
        "3 s, one core), held nearest 148 / 138 / 138 ms and the far rows' plain search "
        "58 / 52 / 48 ms on 1.0 / 1.2 / 1.6 m cells, 0.5-0.8 m slower (178-218 ms). The "
        "hash-table grid of earlier rounds was fastest at 1.0 m")
    knn_grid_cell_m: float | None = Field(
        1.6, gt=0, description="sparse backend: cell of a second hash grid per scan, built "
        "on its first k-nearest-neighbour search (the surfaces: num_neighbors / "
        "far_pair_num_neighbors of a point), for those searches only; None: grid_cell_m. "
        "Speed only, the searches are exact at any size (the same neighbours in the same "
        "order, but for points at exactly the same distance, which come in the order their "
        "cells are visited: every such search of the register stage identical on 1.0, 1.3, "
        "1.6 and 2.0 m cells on three boulevard clips; on the hard street, 128 x 1800, 2 of "
        "1.55 M had two equidistant neighbours swapped, and its registrations stayed "
        "bit-identical). WHY: "
        "the 10th nearest 0.3 m centroid lies beyond 1 m for about half the points of a "
        "64-beam scan (sparse far rings), so on 1.0 m cells most searches looped over a "
        "second shell of up to 98 cells; the k-nearest searches of the register stage's "
        "surfaces took 0.44 / 0.27 / 1.28 s (roadside unit 3 s, base 3 s, seed 2's roadside "
        "unit 10 s, one core) on 1.0 m cells, 0.34 / 0.21 / 1.05 s on 1.6 m ones (1.3 m "
        "0.38 / 0.22 / 1.09, 2.0 m about as 1.6 m); the nearest-neighbour searches of GICP "
        "use grid_cell_m (1.6 m too: then both are one grid)")
    max_iterations: int = Field(30, ge=1)
    num_threads: int = Field(1, ge=1, description="small_gicp / open3d: threads per GICP "
                             "call; one leaves the other cores to the other clips of a run "
                             "(the sparse backend searches on the calling thread; the stage's "
                             "workers run frames in parallel)")
    warm_start: bool = Field(True, description="start each frame from the previous frame's "
                             "accepted correction (and from eq. 1a if that fails)")

    def far_pair(self) -> GicpSection | None:
        """The settings of a far cross pair (``far_pair_num_neighbors``), None where they
        are every pair's."""
        k = self.far_pair_num_neighbors
        if k is None or k == self.num_neighbors:
            return None
        return self.model_copy(update={"num_neighbors": k, "far_pair_num_neighbors": None})

    def range_m(self, reference: bool) -> float:
        """How far an agent's scan keeps its points: ``reference_max_range_m`` for the
        reference agent (the target of the cross pairs) where set, else ``max_range_m``."""
        if reference and self.reference_max_range_m is not None:
            return self.reference_max_range_m
        return self.max_range_m


class QualitySection(Section):
    """When one GICP result is trusted (else the eq. 1a estimate is kept)."""

    fitness_distance_m: float = Field(0.5, gt=0, description="inlier: nearest target point "
                                      "within this distance")
    min_fitness: float = Field(0.2, ge=0, le=1, description="fraction of the (downsampled) "
                               "source points that must be inliers")
    min_inliers: int = Field(300, ge=0)
    max_correction_m: float = Field(1.5, gt=0, description="more than the poses and "
                                    "extrinsics can be wrong by")
    max_correction_deg: float = Field(5.0, gt=0)
    min_observability: float = Field(
        0.02, ge=0, le=1, description="per-frame mode (solve.enabled off): reject when the "
        "overlapping surfaces leave a translation direction unconstrained (corridor, open "
        "road); with the clip solve the information matrix weighs it instead")

    def gated(self, gate: bool) -> QualitySection:
        """These limits, without the degeneracy test when ``gate`` is off (the clip solve
        weighs each direction by its information instead)."""
        return self if gate else self.model_copy(update={"min_observability": 0.0})


class StaticSection(Section):
    """What moves is removed before GICP (the static scene only)."""

    enabled: bool = Field(True, description="remove moving things before GICP")
    use_annotations: bool = Field(True, description="remove the scan's annotated boxes")
    box_margin_m: float = Field(0.3, ge=0, description="annotated boxes are grown by this")
    keep_still_boxes_mps: float | None = Field(
        0.1, ge=0, description="an annotated box whose own annotated speed over ground (the "
        "norm of its 3-D velocity, m/s) is below this stays in the scan: a parked car is "
        "static scene (at 0.1 m/s a box moves 1 cm in a 10 Hz scan period); None: every "
        "annotated box is removed. A box without a velocity (NaN, or no velocity columns) is "
        "always removed; an annotated speed is trusted, not checked against the box's track, "
        "so velocities relative to the moving sensor must not be given. WHY: two vehicles 50 m "
        "apart on a street of walls see each block end face from one side only while it "
        "stands between them, so the parked cars' front and back faces and the poles are what "
        "fixes the pair along the street; with the parked cars removed, GICP started at the "
        "true pose ended ~5 cm off along the street (issue #21, docs/registration.md 'Far "
        "pairs: what fixes them along the street'). A recording whose annotated velocities "
        "are too noisy to tell a parked car sets a smaller value or None")
    body_margin_m: float = Field(0.6, ge=0, description="other agents' declared bodies, "
                                 "placed by their INS poses, are grown by this")
    dynamic: Literal["auto", "on", "off"] = Field(
        "auto", description="remove points inconsistent with the neighbouring scans of the "
        "same agent; auto: in frames without annotations")
    dynamic_residual_m: float = Field(0.5, gt=0, description="a point farther than this from "
                                      "the earlier AND the later neighbouring scans is moving")
    dynamic_neighbours: int = Field(2, ge=1, description="scans on each side compared")
    dynamic_voxel_m: float = Field(0.25, gt=0, description="voxel of the neighbouring scans")
    dynamic_object_fraction: float = Field(
        0.25, gt=0, le=1, description="an above-ground object (connected in bird's-eye view) "
        "with this fraction of moving points is removed whole (1: per point only)")


class OdometrySection(Section):
    """Each agent's own scan-to-scan GICP (hand-eye: separates extrinsic from INS error)."""

    every: int = Field(5, ge=0, description="every n frames (0: off)")
    gap: int = Field(5, ge=1, description="frames between the two scans of a pair")
    straight_every: int = Field(
        5, ge=1, description="on straight driving (turning less than solve.straight_deg over "
        "the gap) only every n frames (10 saves a third of the odometry on the hard street but "
        "its extrinsic ends 1.1 cm off instead of 0.9: straight pairs carry the non-holonomic "
        "yaw)")


class StationarySection(Section):
    """An agent that does not move (a roadside unit): its INS track says so, never its name.

    Its LiDAR sees the same static scene in every frame, so its scan is read, filtered and
    prepared (voxels, neighbour grid, the surfaces GICP computes as it needs them) on one
    frame in ``reuse_frames`` and that cloud stands for it in the frames between. WHY: a
    roadside unit 40-70 m from the other agents is a far pair, aligned again with every
    co-visible centroid (``gicp.sample_min_pairs``), and the k-nearest-neighbour surfaces of
    all of them were computed anew for every frame. A frame used by the agent's own odometry
    always gets its own scan (two copies of one scan would be a perfect, meaningless
    odometry pair)."""

    reuse_frames: int = Field(
        5, ge=1, description="a stationary agent's scan is prepared on every n-th of its "
        "frames (and on its odometry frames) and reused by the frames between; 1: every frame "
        "its own scan (the behaviour before)")
    inherit_surfaces: bool = Field(
        True, description="sparse backend, with stationary.reuse_frames > 1 (the scans it "
        "prepares are the ones linked): a stationary agent's prepared scan takes each "
        "surface (normal, planarity) from its previous prepared scan where the point is in "
        "both, bit-identical, and no point that is in only one of them lies within its k-th "
        "neighbour's distance: the same k nearest neighbours, the same surface (the results "
        "do not change), without the search. Speed only; false: every scan searches its own")
    max_motion_m: float = Field(
        0.02, ge=0, description="stationary: every INS position of the clip within this of "
        "the first one")
    max_rotation_deg: float = Field(
        0.05, ge=0, description="stationary: every INS attitude of the clip within this of "
        "the first one")
    dense_after_short_sample: bool = Field(
        True, description="a cross pair whose source is a stationary agent is aligned as "
        "gicp.dense_after_short_sample says (every co-visible centroid at once, from the warm "
        "start, without the sample pass, after a frame whose sample was short), whatever "
        "that setting is. WHY: a roadside unit 40-70 m away is short in nearly every frame, "
        "its sample pass was spent for nothing, and its dense rows and their surfaces are "
        "its anchor scan's, computed once per reuse_frames. Roadside unit 10 s: GICP "
        "source-point iterations 11.6 M -> 8.5 M, rsu 54 -> 55 of 100 within 3 cm / 0.1 deg, "
        "51 accepted, median 2.53 -> 2.52 cm; 3 s: 13 -> 16 of 30 within, median 3.48 -> "
        "2.93 cm, black's median 0.98 -> 1.00 cm. The gicp-wide setting failed on a moving "
        "far pair (black 50 m ahead), which this one leaves alone")
    far_pair_surfaces: bool = Field(
        True, description="a cross pair with a stationary agent (either side) is aligned "
        "on the far pairs' surfaces (gicp.far_pair_num_neighbors) at any range, not only "
        "beyond gicp.far_pair_beyond_m. WHY: a roadside unit's LiDAR looks down from a mast "
        "on what it shares with the other agent, so its rings on the road and the walls are "
        "far apart even where the vehicle is near; 10-neighbour surfaces of its 0.3 m "
        "centroids span several rings and bend over edges, and a vehicle leaving the mast "
        "(12-45 m) was aligned +4.7 cm (median, the same sign for 2.8 s) along the street, "
        "which the clip solve cannot tell from red's INS error (seed 2's roadside unit, 10 "
        "s: 31 frames 3.0-4.7 cm off). Safety bar (48 boulevard clips and the hard street, "
        "10 with a roadside unit, seeds 1-5, 3 and 10 s): within / accepted / wrong 3783 / "
        "3183 / 0 -> 3809 / 3195 / 0; seed 2's roadside unit 10 s 69 -> 93 within, the "
        "roadside unit 3 s accepted 9 -> 15; the rsu pairs' medians at 10 s 0.39-0.85 -> "
        "0.14-0.33 cm; the 40 clips without a roadside unit identical. Lower by one frame: "
        "seed 2's 3 s rsu within 30 -> 29 (3.01 cm, 63 m away), seed 2's 10 s black accepted "
        "98 -> 97, seed 5's 3 s rsu accepted 8 -> 7. Not measured on a parked vehicle (also "
        "stationary); false: the range decides alone, as for moving agents")
    translation_eps_m: float | None = Field(
        0.003, gt=0, description="a stationary agent's cross pairs stop GICP when the "
        "translation step is below this (and the rotation step below 0.1 deg); None: as "
        "every other pair (gicp.fallback_translation_eps_m, 1 mm). WHY: a roadside unit "
        "40-70 m away is aligned on every co-visible centroid and slides along its weak "
        "direction (translation observability 0.01-0.02) in steps shrinking by about a fifth "
        "per iteration; the last millimetres say nothing the clip solve does not already "
        "discount there. Roadside unit 10 s: its GICP iterations 740 -> 512, rsu 55 -> 59 of "
        "100 within 3 cm / 0.1 deg, 51 accepted, median 2.52 -> 2.30 cm; 3 s: 240 -> 192, "
        "16 of 30 within either way, median 2.93 -> 2.87 cm. On 11 clips with a roadside unit "
        "(seeds 1-3, INS drift, INS step, no turn, ahead 20 m; 3 and 10 s) no accepted count "
        "dropped, none more accepted outside 3 cm / 0.1 deg, medians within 0.05 cm or "
        "better. gicp.fallback_translation_eps_m at 3 mm for every pair failed the bar on a "
        "moving far pair (black 50 m behind), which this one leaves alone")
    max_iterations: int | None = Field(
        None, ge=1, description="a stationary agent's cross pairs: GICP iterations at most; "
        "None: gicp.max_iterations. 10 (with translation_eps_m 3 mm) passed on the 11 "
        "roadside-unit clips (roadside unit 3 s iterations 192 -> 111, 10 s 512 -> 412) but "
        "15 lost a frame within 3 cm on one (16 -> 15 of 30) and black's median grew by up "
        "to 0.06 cm: too thin a margin for a default")
    dense_cell_m: float | None = Field(
        None, gt=0, description="a stationary agent's dense pass (dense_after_short_sample) "
        "aligns the co-visible centroids of a spread sample at this cell (and of its own "
        "sample) instead of every one; None: every one. 0.45 m halves the roadside unit's "
        "GICP time (source-point iterations 3.2 M -> 1.5 M at 3 s, 7.4 M -> 4.2 M at 10 s) "
        "but is not the default: on the 11 roadside-unit clips it lost accepted frames (INS "
        "step 3 s: black 28 -> 27; seed 2 10 s: black 99 -> 98, rsu 51 -> 50; seed 3 10 s: "
        "rsu 50 -> 49 and one more accepted outside 3 cm); 0.6 m the same way")
    warm_any_observability: bool = Field(
        False, description="a stationary agent's next frame starts from this frame's "
        "accepted correction whatever its translation observability (else only at "
        "quality.min_observability or more, as every other agent). Not the default: a "
        "roadside unit's pairs (observability 0.01-0.02) then start where the previous frame "
        "slid to; 3 s clip: rsu 16 -> 11 of 30 within, median 2.93 -> 4.17 cm")


class SolveSection(Section):
    """The clip solve: constant extrinsic corrections + a smooth INS error per agent."""

    enabled: bool = Field(True, description="fuse the frames; off: frame by frame with the "
                          "quality gate")
    relative: bool = Field(
        True, description="per-frame relative transforms from a solve of the cross-agent "
        "frames alone (odometry, non-holonomic and ground constraints only split the "
        "extrinsic); off: one solve gives both")
    knot_s: float = Field(1.0, gt=0, description="INS error knots (piecewise linear) every")
    prior_ext_m: float = Field(0.3, gt=0, description="extrinsic correction prior, 1-sigma")
    prior_ext_deg: float = Field(2.0, gt=0, description="extrinsic correction prior, 1-sigma")
    prior_att_deg: float = Field(0.05, gt=0, description="INS attitude bias prior, 1-sigma")
    prior_pos_m: float = Field(2.0, gt=0, description="INS position error prior, 1-sigma")
    prior_drift_mps: float = Field(0.2, gt=0, description="INS drift rate prior, 1-sigma")
    prior_drift_accel: float = Field(
        0.01, gt=0, description="INS drift rate change (m/s^2), 1-sigma: an INS velocity error "
        "changes by about a centimetre per second per second")
    robust_scale: float = Field(3.0, gt=0, description="Cauchy scale of a frame's whitened "
                                "residual (standard deviations)")
    outlier_p: float = Field(1e-3, gt=0, lt=1, description="leave-one-out test: a frame is an "
                             "outlier above the chi^2(6) quantile 1 - p")
    irls_iterations: int = Field(4, ge=1)
    max_iterations: int = Field(20, ge=1, description="Gauss-Newton steps per reweighting")
    min_for_variance: int = Field(20, ge=1, description="measurements needed to estimate the "
                                  "variance factor")
    odometry_weight: float = Field(1.0, gt=0)
    floor_m: float = Field(0.01, gt=0, description="a GICP result's error floor, whatever its "
                           "Hessian says (voxels, deskew residuals, what filtering left)")
    floor_deg: float = Field(0.02, gt=0, description="... and its rotation floor")
    floor_range_m: float | None = Field(
        40.0, gt=0, description="a cross-agent result's floor grows in proportion to the "
        "range between the two LiDARs beyond this (the far agent's point spacing on what "
        "both see: at 40 m a 1024-column LiDAR's columns are 0.25 m apart, most of a 0.3 m "
        "voxel, so its centroids shift with where its rings fall, in every direction; a bias "
        "GICP's Hessian does not show). None: the same floor at every range. 20 m until "
        "2026-11-28, sized on the 3-19 cm bias the reference's 80 m range cut caused; with "
        "the reference's scans to 120 m, on 26 far clips (50 m behind / ahead, the roadside "
        "unit; seeds 1-5, 3 and 10 s) 20 m accepted 789 frames, none outside 3 cm / 0.1 deg, "
        "30 / 40 / None alone 1252 / 1601 / 1738 with 21 / 42 / 63 outside: the far pairs' "
        "bias is along the street, which weak_geometry_beyond_m covers. With it, 40 m keeps "
        "every clip's within-target count (None lost 4 of 30 on one 3 s clip) and none "
        "outside on the whole bar (bench_register.py --coop --bar)")
    degenerate_ratio: float = Field(
        0.02, ge=0, lt=1, description="a GICP result carries no information in directions "
        "weaker than this fraction of its strongest (the slide along a street)")
    nonholonomic_deg: float = Field(
        0.1, gt=0, description="on straight driving the body moves along its own x axis; "
        "1-sigma (deg) of that direction per straight odometry pair (fixes the extrinsic's yaw "
        "and pitch without the INS heading)")
    straight_deg: float = Field(1.0, gt=0, description="an odometry pair turning less than "
                                "this is straight")
    nonholonomic_min_m: float = Field(2.0, gt=0, description="a straight pair moving less "
                                      "than this says nothing about its direction")
    ground_sigma_m: float = Field(
        0.02, gt=0, description="the LiDAR's measured height above the ground vs the agent's "
        "declared body (ground to roof) fixes the extrinsic's z; 1-sigma (suspension, crown)")
    final_max_std_m: float = Field(0.02, gt=0, description="a frame's final estimate is "
                                   "accepted when its 1-sigma (translation) is below this")
    final_max_std_deg: float = Field(0.05, gt=0, description="... and its rotation 1-sigma")
    max_bridge_s: float = Field(
        3.0, gt=0, description="no extrapolation: a direction a frame's own GICP did not "
        "observe (own 1-sigma above final_max_std_m/deg: blind along the street, or no "
        "measurement) is taken from the clip solve only when frames that observed it lie "
        "before AND after it within this many seconds; otherwise the frame is not accepted. "
        "On the test clip the frames that do not observe every direction themselves come in "
        "runs of at most 4 (0.4 s), so its targets hold for any bridge over 0.5 s; 3 s is "
        "about one pole spacing (30-45 m) at 10 m/s: a blind stretch between two poles is "
        "bridged, a longer one (or the clip's ends) is not")
    correlation_s: float = Field(
        2.0, gt=0, description="GICP errors of consecutive frames are correlated (the same "
        "facades and poles, the same voxel aliasing): in the reported 1-sigma of a frame's "
        "clip estimate the frames within this many seconds count as one measurement (the "
        "estimate itself is unchanged). Measured on the hard street: runs of 1-2 s of frames "
        "off by 4-19 cm with the same sign while GICP claims 1.6 cm; 1 s still accepted frames "
        "3-5 cm off at the edge of such a run (black 20 m behind), 2 s none")
    own_bound: bool = Field(
        True, description="a frame's reported 1-sigma is at most what its own GICP result "
        "gives (honestly stated: variance factor, floor, weak_geometry_ratio; plus its "
        "distance to the clip estimate), for inliers that observe every direction: the "
        "clip covariance counts correlated frames once per correlation_s, so the clip's end "
        "frames (neighbours on one side) were reported twice as uncertain as their own "
        "measurement (demo clip: 2.0-2.1 cm for frames measured to 1.0 cm, 0.3 cm off)")
    weak_geometry_ratio: float | None = Field(
        0.08, gt=0, lt=1, description="a GICP result's Hessian claims too little along a "
        "direction its surfaces barely constrain (a voxel or sampling bias is shared by the "
        "whole surface): along each translation eigen-direction (rotation eliminated) weaker "
        "than this fraction of the strongest, its own covariance (own_bound) gets "
        "floor_m^2 (this / ratio - 1). Measured on the cooperative boulevard (12 clips, "
        "1200 frames at 0.01-0.03): errors along the street 0.9-1.5x the claim rms, up to "
        "3.7x (3.4 cm off claiming 1.05 cm); at 0.03-0.05 and on the demo street "
        "(0.11-0.20) within 0.45x. With 0.08 seed 2's 3.4 cm frame gets 2.5 cm own 1-sigma "
        "(not accepted; 0.05 accepted it, 0.06 did not) and none of 28 boulevard variations, "
        "two hard-street clips and the demo accepts a frame outside 3 cm / 0.1 deg; 0.1 and "
        "above gave back most of the gain (INS step, 3 s: 23/30 accepted, 27 with 0.08). "
        "None: no floor")
    stationary_weak_geometry: bool = Field(
        True, description="in the reported clip covariance, a frame of a pair with a "
        "stationary agent (stationary.max_motion_m) is whitened with its weak-geometry "
        "floor (weak_geometry_ratio) as well, not only in its own bound: a stationary agent "
        "sees the same surfaces from the same place all clip long, so its pair's bias along "
        "a weak direction repeats frame after frame and the clip cannot average it away. "
        "Measured with a roadside unit 12-39 m from the reference (seed 2, 10 s, translation "
        "observability 0.006-0.015): 26 consecutive frames 2-9 cm off along the street, "
        "same sign, each claiming 0.5 cm + the 1 cm floor; the clip reported 1.0-1.5 cm and "
        "accepted 28 frames 3.0-4.7 cm off. Only the reported 1-sigma changes, never the "
        "estimate; pairs without a stationary agent are untouched")
    weak_geometry_beyond_m: float | None = Field(
        30.0, ge=0, description="in the reported clip covariance, a cross frame whose two "
        "LiDARs are farther apart than this is whitened with its weak-geometry floor "
        "(weak_geometry_ratio) as well, as a stationary pair's are "
        "(stationary_weak_geometry), still counted once per correlation_s; only the "
        "reported 1-sigma changes, never the estimate. Why: at 40-50 m what fixes a pair "
        "along the street is a few poles and car flanks seen in the far agent's sparse "
        "rings, and their bias repeats while the agents keep their distance: black 50 m "
        "behind (seed 3, 10 s) was 3-19 cm short along the street for 4 s, each frame "
        "claiming ~0.5 cm there (translation observability 0.005-0.01). Pairs at 20 m "
        "(0.01-0.03, errors 0.9-1.5x the claim) need no such floor: applied to every cross "
        "frame it cost the 20 m-behind vehicle up to 88 of 98 accepted frames (seed 2, "
        "10 s), hence a range well above theirs. With floor_range_m 40, on the safety bar "
        "(bench_register.py --coop --bar --seeds 3 4 5 --bar-street: 48 clips and the hard "
        "street; 2026-11-28) accepted 2285 -> 2855 frames, none outside 3 cm / 0.1 deg, no "
        "clip's within-target count lower (50 m behind 0 -> 80 of 100 at 10 s). None: off; "
        "0: every cross frame")
    stationary_correlation_s: float | None = Field(
        3.0, gt=0, description="... and the frames of such a pair within this many seconds "
        "count as one measurement (correlation_s for the others; None: correlation_s). The "
        "same-sign run above lasted 2.6 s. On 11 roadside-unit clips (seeds 1-3, INS drift / "
        "step, no turn, ahead 20 m; 3 and 10 s) the rsu pair's accepted frames go 211 -> 83, "
        "none outside 3 cm / 0.1 deg (before: 29; worst accepted 4.7 -> 1.4 cm); 2.5 s kept "
        "105 (worst 1.65 cm), 2.2 s accepted 8 outside, 2 s 19, 4 s kept 36; without the "
        "weak-geometry floor 5 s still accepted 24 outside, the whole clip 7. The other "
        "vehicle's counts the same on all 11")
    ins_step_m: float = Field(
        0.05, gt=0, description="an INS step: a pose-to-pose displacement that differs from "
        "the mean of its two neighbouring displacements (scaled by time) by more than this; "
        "the clip solve then gives that agent's INS error a free offset from the step on "
        "(not absorbed into the extrinsic) and the report notes it")


class CalibrationSection(Section):
    """When the clip's refined LiDAR extrinsic is usable (else the published one stays)."""

    max_variance_factor: float = Field(
        4.0, gt=0, description="the fit must be consistent: the clip's variance factor "
        "(median GICP residual chi^2 / its expectation) at most this")
    max_outlier_fraction: float = Field(
        0.1, ge=0, le=1, description="... and at most this fraction of the frames the agent "
        "takes part in are leave-one-out outliers (a run of them is an unmodelled INS error)")
    require_all: bool = Field(
        False, description="usable only when every component (rx ry rz tx ty tz) was "
        "determined. Off (default): the components the clip determined are used and the "
        "others keep the published value (named in the reason; their unknown error is not in "
        "the 1-sigma). Driving straight, a cooperative vehicle's extrinsic x / y cannot be "
        "told from an INS offset while its yaw can: keeping the whole published extrinsic "
        "then put the yaw error (0.4 deg on the boulevard) into every consumer of the agent's "
        "pose, its cameras included")
    significance: float = Field(
        2.0, gt=0, description="a correction whose Mahalanobis norm over the determined "
        "components is below this (in sigma, per chi^2 quantile of that dimension) is not "
        "significant: the published extrinsic is kept (correction zeroed, the clip confirms "
        "the published one within its 1-sigma)")
    determined_fraction: float = Field(
        0.3, gt=0, le=1, description="a component is refined when the clip reduced its "
        "1-sigma below this fraction of the prior; the others keep the published value")
    max_std_m: float = Field(0.03, gt=0, description="usable when the refined translation "
                             "components' 1-sigma are below this")
    max_std_deg: float = Field(0.1, gt=0, description="... and the rotation components'")


class RedeskewSection(Section):
    """Deskew an agent's scans again when the clip found its LiDAR rotation wrong."""

    enabled: bool = Field(
        True, description="when the clip finds an agent's LiDAR rotation wrong by enough to "
        "smear its deskewed scans (min_shift_m), deskew that agent's scans again with the "
        "refined extrinsic (deskew's kernel, backwards then forwards) and measure and solve "
        "once more (twice the GICP time, spent only then). Deskew moves each point by the ego "
        "motion expressed in the LiDAR frame, so a yaw error of the extrinsic turns that "
        "motion: a 1.5 deg error at 16 m/s biased every cooperative GICP by 2.4 cm sideways")
    min_shift_m: float = Field(
        0.02, ge=0, description="re-deskew when the refined rotation (all of rx ry rz "
        "determined, the fit consistent) moves the points at the end of a scan by at least "
        "this (rotation correction times the agent's largest travel during one scan)")


class IntraSection(Section):
    """An agent's secondary LiDARs refined against its primary one."""

    enabled: bool = Field(True, description="refine every secondary LiDAR of an agent "
                          "against its primary (register.intra_stage)")
    frames: int = Field(3, ge=1, description="frame pairs pooled per secondary LiDAR")


class RegisterConfig(StageConfig):
    """Parameters of the register stage (hashed into the manifest)."""

    RENAMED: ClassVar[dict[str, str]] = {
        "backend": "gicp.backend", "voxel_m": "gicp.voxel_m",
        "source_voxel_m": "gicp.source_voxel_m", "max_range_m": "gicp.max_range_m",
        "num_neighbors": "gicp.num_neighbors",
        "max_correspondence_m": "gicp.max_correspondence_m",
        "max_iterations": "gicp.max_iterations", "warm_start": "gicp.warm_start",
        **{k: f"quality.{k}" for k in ("fitness_distance_m", "min_fitness", "min_inliers",
                                       "max_correction_m", "max_correction_deg",
                                       "min_observability")},
        "static_only": "static.enabled", "dynamic_filter": "static.dynamic",
        **{k: f"static.{k}" for k in ("use_annotations", "box_margin_m", "body_margin_m",
                                      "dynamic_residual_m", "dynamic_neighbours",
                                      "dynamic_voxel_m", "dynamic_object_fraction")},
        "odometry_every": "odometry.every", "odometry_gap": "odometry.gap",
        "odometry_straight_every": "odometry.straight_every",
        "odometry_turn_deg": "solve.straight_deg",
        "clip_solve": "solve.enabled", "relative_solve": "solve.relative",
        "gicp_floor_m": "solve.floor_m", "gicp_floor_deg": "solve.floor_deg",
        "gicp_correlation_s": "solve.correlation_s",
        **{k: f"solve.{k}" for k in ("knot_s", "prior_ext_m", "prior_ext_deg", "prior_att_deg",
                                     "prior_pos_m", "prior_drift_mps", "prior_drift_accel",
                                     "robust_scale", "outlier_p", "irls_iterations",
                                     "degenerate_ratio", "nonholonomic_deg", "ground_sigma_m",
                                     "final_max_std_m", "final_max_std_deg", "max_bridge_s",
                                     "ins_step_m")},
        **{f"refined_{k}": f"calibration.{k}" for k in (
            "max_variance_factor", "max_outlier_fraction", "require_all", "significance",
            "determined_fraction", "max_std_m", "max_std_deg")},
        "redeskew": "redeskew.enabled", "redeskew_min_shift_m": "redeskew.min_shift_m",
        "intra_agent": "intra.enabled", "intra_frames": "intra.frames",
    }

    sensor: str | None = Field(None, description="LiDAR to register; default LIDAR_TOP or "
                               "the agent's only LiDAR")
    pair_tolerance_ns: int = Field(1_000_000, ge=0, description="scan starts closer than "
                                   "this are one pair")
    covisible: bool = Field(
        True, description="GICP between two agents on the surfaces both see from the same "
        "side only: a pole or parked car between the agents is seen from opposite sides, two "
        "surfaces a diameter apart that GICP pulls together (measured on the cooperative "
        "boulevard: 2 cm along the street with the agents 20 m apart, 9-12 cm at 50 m)")
    workers: int = Field(
        0, ge=0, description="threads for the per-frame work: reading, static-scene "
        "filtering, preparing the clouds and the agents' odometry GICP run a few frames "
        "ahead on a pool while the cross-agent GICP runs in frame order (each frame starts "
        "from the previous one's accepted correction). 0: the cores this process may use "
        "(its affinity mask, a Dask worker's share), at most 8. The results are the same "
        "for any number (tests/test_register_speed.py)")
    bev_frame: int | None = Field(None, description="reference frame of the BEV picture "
                                  "(default: the middle pair)")
    write_bev: bool = Field(True, description="render the BEV and timeline pictures")
    gicp: GicpSection = Field(default_factory=GicpSection)
    quality: QualitySection = Field(default_factory=QualitySection)
    static: StaticSection = Field(default_factory=StaticSection)
    odometry: OdometrySection = Field(default_factory=OdometrySection)
    stationary: StationarySection = Field(default_factory=StationarySection)
    solve: SolveSection = Field(default_factory=SolveSection)
    calibration: CalibrationSection = Field(default_factory=CalibrationSection)
    redeskew: RedeskewSection = Field(default_factory=RedeskewSection)
    intra: IntraSection = Field(default_factory=IntraSection)
