"""GICP backends behind one interface (main paper eq. 1b: T_init -> GICP -> T_refine).

Three implementations of Generalized-ICP [Segal et al.]: ``sparse`` (default; :mod:`sparse`: a
spread sample of the source, surfaces computed only where correspondences land, more
centroids where the sample finds too few, searches on a hash grid; 4.5x faster per pair than
the small_gicp backend on 239k-point scans, 0.036 against 0.160 s), small_gicp (every point
of both clouds) and Open3D. Each cloud is prepared ONCE (voxel downsampling, per-point
covariances or a lazy surface store, k-d tree or grid) and reused: the reference agent's
scan is the target of every other agent's scan in the same frame, and small_gicp's one-call
``align`` on NumPy arrays would redo that work every time (60-75 % of its cost).
All report the same quality figures, computed the same way (nearest neighbour of each
transformed source point -- of its sample for ``sparse`` -- in the target within a distance),
so thresholds mean the same whichever backend ran, and the same information matrix: the GICP
Hessian with plane-regularised covariances (eigenvalues 1e-3, 1, 1 as small_gicp sets them),
for a LEFT perturbation ``exp(xi) T`` of ``T_target_source`` in the target frame, ``xi = [rot,
trans]`` (small_gicp's own Hessian is for a right perturbation and is converted; Open3D
exposes none, so it is computed from its covariances at the solution).

Only finite points reach a backend (voxel downsampling drops NaN and inf; ``prepare_points``
refuses anything else), so a backend never sees the NaN that crashed Open3D's GICP.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal, Protocol

import numpy as np

from v2xlake.tasks.geometry import se3_adjoint
from v2xlake.tasks.register.config import GicpSection
from v2xlake.tasks.register.voxel import VoxelGrid, cell_keys, voxel_downsample

if TYPE_CHECKING:
    from v2xlake.tasks.register.sparse import SparseOutcome

BackendName = Literal["small_gicp", "open3d", "sparse"]
DEFAULT_GICP = GicpSection()  # frozen: one shared default
PLANE_EPS = 1e-3  # smallest eigenvalue of a plane-regularised covariance (small_gicp's)


@dataclass
class Prepared:
    """A downsampled cloud with covariances and a search structure, backend specific."""

    points: np.ndarray  # (M, 3) float64 downsampled
    handle: Any  # backend cloud
    tree: Any  # backend search structure
    sample: np.ndarray | None = None  # as a source, only these rows are aligned and scored
    covisible_with: np.ndarray | None = None  # as a target: pairs kept where seen from here
    # as a source (sparse backend): align every co-visible row at once, no sample pass first
    # (the caller's copy of a cross pair's source: the previous frame's sample was short)
    dense_first: bool = False
    # as a source (sparse backend): this pair's GICP stopping rule where it is not the
    # backend's (a stationary agent's pairs, ``stationary.translation_eps_m`` /
    # ``stationary.max_iterations``); None: the backend's settings
    translation_eps_m: float | None = None
    max_iterations: int | None = None
    # as a source (sparse backend): its dense pass (``dense_first``) aligns the co-visible
    # rows of a spread sample at this cell (and the sample's) instead of every one
    dense_cell_m: float | None = None
    # as a source (sparse backend): each spot's correspondences from the scan that sampled
    # it more densely (``gicp.far_pair_denser_side``, :func:`sparse.align_sparse`)
    denser_side: bool = False

    def rows(self) -> np.ndarray:
        """The rows a source contributes: its sample, or every point."""
        return self.sample if self.sample is not None else np.arange(len(self.points))


@dataclass(frozen=True)
class AlignOutcome:
    T: np.ndarray  # 4x4 T_target_source
    converged: bool
    iterations: int
    H: np.ndarray | None = None  # 6x6 Gauss-Newton Hessian at the solution [rot, trans]
    # squared distance of each source row (``Prepared.rows``) to its nearest target point
    # at the last linearisation (inf beyond the correspondence distance), where the backend
    # has it: the quality figures then need no search of their own
    sq_dist: np.ndarray | None = None
    # sparse backend: whether the source's sample found (sample pass) or would have found
    # (read from the dense alignment's last search) fewer than ``sample_min_pairs``
    sample_short: bool = False


class RegistrationBackend(Protocol):
    name: str
    params: GicpSection

    def prepare(self, xyz: np.ndarray, *, as_target: bool = True) -> Prepared: ...

    def prepare_points(self, pts: np.ndarray) -> Prepared: ...

    def align(self, target: Prepared, source: Prepared, init: np.ndarray) -> AlignOutcome: ...

    def nearest_sq_dist(self, target: Prepared, query: np.ndarray,
                        max_dist_m: float = np.inf) -> np.ndarray:
        """Squared distance of each query point to its nearest target point; a distance
        beyond ``max_dist_m`` may come back as inf (the quality figures count inliers only)."""
        ...

    def prepare_covisible(self, pts: np.ndarray, other_origin: np.ndarray, min_keep: int,
                          base: Prepared | None = None, *, as_target: bool = False
                          ) -> Prepared:
        """Only what the LiDAR at ``other_origin`` sees from the same side. ``base``: the
        same points already prepared by ``prepare_points``, which a backend may share;
        ``as_target``: the cloud will only be a target (a backend may skip what only a
        source uses)."""
        ...


def _masked_prepare(backend: RegistrationBackend, pts: np.ndarray, other_origin: np.ndarray,
                    min_keep: int) -> Prepared:
    """Only what the LiDAR at ``other_origin`` sees from the same side (:mod:`covisible`),
    or the whole scan where less than ``max(min_keep, 30 %)`` of it would remain."""
    from v2xlake.tasks.register.covisible import covisible_mask

    keep = covisible_mask(pts, other_origin)
    if keep.sum() >= max(min_keep, 0.3 * len(keep)):
        pts = pts[keep]
    return backend.prepare_points(pts)


def _downsample(xyz: np.ndarray, p: GicpSection, as_target: bool) -> np.ndarray:
    return voxel_downsample(xyz, p.voxel_m if as_target else p.source_voxel_m, p.max_range_m)


def _finite(pts: np.ndarray) -> np.ndarray:
    p = np.ascontiguousarray(np.asarray(pts, dtype=np.float64).reshape(-1, 3))
    if not np.isfinite(p).all():
        raise ValueError("non-finite points must not reach a GICP backend")
    return p


def right_to_left_information(H: np.ndarray, T: np.ndarray) -> np.ndarray:
    """A Hessian for ``T exp(d)`` ([rot, trans], source frame) as one for ``exp(xi) T``:
    ``xi = Ad_T d``, so ``H_left = Ad_T^-T H Ad_T^-1``."""
    inv = np.linalg.inv(se3_adjoint(T))
    out = inv.T @ H @ inv
    return np.asarray(0.5 * (out + out.T))


def _plane_cov(cov: np.ndarray) -> np.ndarray:
    """Covariances with eigenvalues replaced by (1e-3, 1, 1) (small_gicp's regularisation)."""
    w, v = np.linalg.eigh(cov)
    del w
    return np.einsum("nij,j,nkj->nik", v, np.array([PLANE_EPS, 1.0, 1.0]), v)


def gicp_information(target_pts: np.ndarray, target_cov: np.ndarray, source_pts: np.ndarray,
                     source_cov: np.ndarray, nn_idx: np.ndarray, nn_d2: np.ndarray,
                     T: np.ndarray, max_dist_m: float) -> np.ndarray:
    """GICP Hessian at ``T`` for a left perturbation, from per-point covariances (plane-
    regularised here) and each source point's nearest target point (``nn_idx``, squared
    distance ``nn_d2`` after moving by ``T``); pairs farther than ``max_dist_m`` left out."""
    ok = nn_d2 <= max_dist_m * max_dist_m
    if not ok.any():
        return np.zeros((6, 6))
    R = T[:3, :3]
    q = source_pts[ok] @ R.T + T[:3, 3]
    c = _plane_cov(target_cov[nn_idx[ok]]) + R @ _plane_cov(source_cov[ok]) @ R.T
    W = np.linalg.inv(c)
    J = np.zeros((len(q), 3, 6))
    J[:, 0, 1], J[:, 0, 2] = q[:, 2], -q[:, 1]
    J[:, 1, 0], J[:, 1, 2] = -q[:, 2], q[:, 0]
    J[:, 2, 0], J[:, 2, 1] = q[:, 1], -q[:, 0]
    J[:, :, 3:] = np.eye(3)
    H = np.einsum("nai,nab,nbj->ij", J, W, J)
    return np.asarray(0.5 * (H + H.T))


class SmallGicpBackend:
    name = "small_gicp"

    def __init__(self, params: GicpSection = DEFAULT_GICP) -> None:
        import small_gicp

        self._sg = small_gicp
        self.params = params

    def prepare(self, xyz: np.ndarray, *, as_target: bool = True) -> Prepared:
        return self.prepare_points(_downsample(xyz, self.params, as_target))

    def prepare_points(self, pts: np.ndarray) -> Prepared:
        sg, p = self._sg, self.params
        pts = _finite(pts)
        cloud = sg.PointCloud(pts)
        tree = sg.KdTree(cloud, num_threads=p.num_threads)
        if len(pts) > p.num_neighbors:
            sg.estimate_covariances(cloud, tree, p.num_neighbors, num_threads=p.num_threads)
        return Prepared(pts, cloud, tree)

    def align(self, target: Prepared, source: Prepared, init: np.ndarray) -> AlignOutcome:
        p = self.params
        r = self._sg.align(target.handle, source.handle, target.tree,
                           init_T_target_source=np.asarray(init, np.float64),
                           registration_type="GICP",
                           max_correspondence_distance=p.max_correspondence_m,
                           num_threads=p.num_threads, max_iterations=p.max_iterations)
        T = np.asarray(r.T_target_source)
        H = np.asarray(r.H, dtype=np.float64)
        H_left = right_to_left_information(H, T) if np.isfinite(T).all() else None
        return AlignOutcome(T, bool(r.converged), int(r.iterations), H_left)

    def nearest_sq_dist(self, target: Prepared, query: np.ndarray,
                        max_dist_m: float = np.inf) -> np.ndarray:
        del max_dist_m  # the k-d tree finds the nearest point at any distance
        _, d2 = target.tree.batch_nearest_neighbor_search(
            np.ascontiguousarray(query, np.float64), num_threads=self.params.num_threads)
        return np.asarray(d2, dtype=np.float64)

    def prepare_covisible(self, pts: np.ndarray, other_origin: np.ndarray, min_keep: int,
                          base: Prepared | None = None, *, as_target: bool = False
                          ) -> Prepared:
        del base, as_target  # the co-visible part is a cloud of its own here
        return _masked_prepare(self, pts, other_origin, min_keep)


class Open3dBackend:
    name = "open3d"

    def __init__(self, params: GicpSection = DEFAULT_GICP) -> None:
        import open3d as o3d

        self._o3d = o3d
        self.params = params

    def prepare(self, xyz: np.ndarray, *, as_target: bool = True) -> Prepared:
        return self.prepare_points(_downsample(xyz, self.params, as_target))

    def prepare_points(self, pts: np.ndarray) -> Prepared:
        o3d, p = self._o3d, self.params
        pts = _finite(pts)
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
        if len(pts) > p.num_neighbors:
            pcd.estimate_covariances(o3d.geometry.KDTreeSearchParamKNN(p.num_neighbors))
        return Prepared(pts, pcd, None)

    def align(self, target: Prepared, source: Prepared, init: np.ndarray) -> AlignOutcome:
        o3d, p = self._o3d, self.params
        reg = o3d.pipelines.registration
        r = reg.registration_generalized_icp(
            source.handle, target.handle, p.max_correspondence_m, np.asarray(init, np.float64),
            reg.TransformationEstimationForGeneralizedICP(),
            reg.ICPConvergenceCriteria(relative_fitness=1e-6, relative_rmse=1e-6,
                                       max_iteration=p.max_iterations))
        T = np.asarray(r.transformation).copy()
        H = None
        if np.isfinite(T).all() and len(source.points) and len(target.points):
            tc = np.asarray(target.handle.covariances)
            sc = np.asarray(source.handle.covariances)
            if len(tc) == len(target.points) and len(sc) == len(source.points):
                idx, d2 = self._nearest(target, source.points @ T[:3, :3].T + T[:3, 3])
                H = gicp_information(target.points, tc, source.points, sc, idx, d2, T,
                                     p.max_correspondence_m)
        return AlignOutcome(T, True, -1, H)

    def _nearest(self, target: Prepared, query: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # the same exact nearest-neighbour figure as small_gicp (SciPy k-d tree, built lazily)
        from scipy.spatial import cKDTree

        if target.tree is None:
            target.tree = cKDTree(target.points)
        d, i = target.tree.query(query, k=1)
        return np.asarray(i, dtype=np.int64), np.asarray(d, dtype=np.float64) ** 2

    def nearest_sq_dist(self, target: Prepared, query: np.ndarray,
                        max_dist_m: float = np.inf) -> np.ndarray:
        del max_dist_m  # the k-d tree finds the nearest point at any distance
        return self._nearest(target, query)[1]

    def prepare_covisible(self, pts: np.ndarray, other_origin: np.ndarray, min_keep: int,
                          base: Prepared | None = None, *, as_target: bool = False
                          ) -> Prepared:
        del base, as_target  # the co-visible part is a cloud of its own here
        return _masked_prepare(self, pts, other_origin, min_keep)


def sample_sq_dist(sample: np.ndarray, dense: np.ndarray, sq_dist: np.ndarray | None
                   ) -> np.ndarray | None:
    """Each ``sample`` row's squared nearest distance from a search of the ``dense`` rows
    (both ascending; ``sq_dist``: one per dense row), NaN where a sample row is not a dense
    row. WHY: a pair aligned on more rows than its sample (a stationary agent's dense pass,
    the fallback after a short sample) has already searched the sample rows in its last
    iteration; the quality figures and the next frame's decision read them from there."""
    if sq_dist is None:
        return None
    out = np.full(len(sample), np.nan)
    if len(sample) == 0 or len(dense) == 0:
        return out
    pos = np.minimum(np.searchsorted(dense, sample), len(dense) - 1)
    there = dense[pos] == sample
    out[there] = sq_dist[pos[there]]
    return out


def pairs_within(sq: np.ndarray | None, max_correspondence_m: float) -> int:
    """How many of the squared distances ``sq`` (:func:`sample_sq_dist`; NaN: none) lie
    within ``max_correspondence_m``; 0 without them. WHY: a pair aligned on every centroid
    without its sample pass still needs to know whether that pass would have been short, to
    decide the next frame; the dense pass's last search answers it without a search of its
    own."""
    return 0 if sq is None else int(np.count_nonzero(sq <= max_correspondence_m ** 2))


class SparseGicpBackend(SmallGicpBackend):
    """GICP on a spread sample of the source with surfaces computed where they are used
    (:mod:`sparse`); its searches (nearest neighbour, k nearest, the quality figure) on a
    hash grid (:class:`voxel.VoxelGrid`): exact like small_gicp's k-d tree, built in a
    sixth of the time, and free of the GIL."""

    name = "sparse"

    def prepare_points(self, pts: np.ndarray) -> Prepared:
        from v2xlake.tasks.register.sparse import Surfaces, spread_sample

        p = self.params
        pts = _finite(pts)
        tree = VoxelGrid(pts, p.grid_cell_m, p.knn_grid_cell_m)
        sample = (spread_sample(pts, p.sample_cell_m) if p.sample_cell_m
                  else np.arange(len(pts), dtype=np.int64))
        return Prepared(pts, Surfaces.empty(len(pts)), tree, sample)

    def own_surfaces(self, base: Prepared, share: bool = True) -> Prepared:
        """``base`` (prepared by this backend's kind) with the same points, grid and sample
        and a surface store of its own, empty: surfaces from another number of neighbours
        (``gicp.far_pair_num_neighbors``) beside the ones ``base`` keeps. ``share``: the
        two stores share their k-nearest-neighbour searches (:class:`sparse.Neighbours`,
        attached to ``base``'s store here): the one with more neighbours keeps its
        searches, the other takes the first columns of those where they exist (the same
        neighbours its own search finds). Either way each store computes the same
        surfaces."""
        from dataclasses import replace

        from v2xlake.tasks.register.sparse import Neighbours, Surfaces

        surf = base.handle
        if share and surf.neighbours is None:
            surf.neighbours = Neighbours.empty(len(base.points))
        return replace(base, handle=Surfaces.empty(len(base.points),
                                                   surf.neighbours if share else None))

    @staticmethod
    def follow(pairs: list[tuple[Prepared | None, Prepared | None]]) -> None:
        """Each (new, old) store of two scans of the same stationary LiDAR: the new one takes
        its surfaces from the old one where they cannot differ (:class:`sparse.Predecessor`,
        the points matched once for all pairs); ``old`` None: the link is dropped."""
        from dataclasses import replace

        from v2xlake.tasks.register.sparse import Predecessor, Surfaces

        link: Predecessor | None = None
        for new, old in pairs:
            if new is None or not isinstance(new.handle, Surfaces):
                continue
            if old is None or not isinstance(old.handle, Surfaces):
                new.handle.pred = None
                continue
            if link is None:
                link = Predecessor.of(new.points, old.points, old.handle)
            new.handle.pred = replace(link, surf=old.handle)

    def align(self, target: Prepared, source: Prepared, init: np.ndarray) -> AlignOutcome:
        """Align the source's sample; where it finds fewer than ``sample_min_pairs``
        correspondences, align again from there with more (co-visible) source centroids
        (:meth:`_fallback_rows`)."""
        p = self.params
        rows = source.rows()
        if source.dense_first and source.sample is not None and p.sample_min_pairs > 0 \
                and p.sample_fallback == "every":
            if source.dense_cell_m is None:
                dense = self._dense_rows(source)
            else:
                from v2xlake.tasks.register.sparse import spread_sample

                dense = self._dense_rows(source, np.union1d(
                    spread_sample(source.points, source.dense_cell_m), rows))
            out = self._align_rows(target, source, dense, init, dense=True)
            sq = sample_sq_dist(rows, dense, out.sq_dist)  # looked up once for both uses
            short = pairs_within(sq, p.max_correspondence_m) < p.sample_min_pairs
            return AlignOutcome(out.T, out.converged, out.iterations, out.H,
                                sq if p.reuse_last_search else None, short)
        out = self._align_rows(target, source, rows, init)
        sq = out.sq_dist
        short = out.pairs < p.sample_min_pairs and source.sample is not None
        if short:
            dense = self._fallback_rows(source, out.pairs, rows, out.sq_dist)
            if len(dense) > len(rows):
                out = self._align_rows(target, source, dense, out.T, dense=True)
                sq = sample_sq_dist(rows, dense, out.sq_dist)
        return AlignOutcome(out.T, out.converged, out.iterations, out.H,
                            sq if p.reuse_last_search else None, short)

    def _fallback_rows(self, source: Prepared, pairs: int, rows: np.ndarray | None = None,
                       sq_dist: np.ndarray | None = None) -> np.ndarray:
        """The source rows of a pair whose sample (``rows``, their squared nearest distances
        ``sq_dist`` at its last search) found only ``pairs`` correspondences.

        ``sample_fallback`` "matched": every centroid in the sample cells whose sample point
        found a correspondence. A far pair's overlap is a small part of its scan: the rest
        finds no correspondence at any density, but aligning every centroid computed the
        surface of all of them (their co-visibility needs it) and searched each one in every
        iteration.

        ``sample_fallback`` "finer": a spread sample whose cell is shrunk by
        ``sqrt(pairs / sample_min_pairs)`` (the correspondences on the overlapping surfaces
        grow as the inverse square of the cell), so it should find about
        ``sample_min_pairs``; every centroid when that cell is not larger than the source
        voxel. WHY: a far pair (a roadside unit 70 m away) found 1,100-1,400 sample
        correspondences, and aligning every centroid instead computed the surface of all of
        them (their co-visibility needs it) and ran GICP on 9x the sample. "every": every
        centroid."""
        p = self.params
        cell = p.sample_cell_m
        if p.sample_fallback == "every" or cell is None or pairs <= 0:
            return self._dense_rows(source)
        if p.sample_fallback == "matched":
            if rows is None or sq_dist is None or len(sq_dist) != len(rows):
                return self._dense_rows(source)
            hit = rows[sq_dist <= p.max_correspondence_m ** 2]
            key = cell_keys(source.points, cell)
            return self._dense_rows(source, np.flatnonzero(np.isin(key, key[hit])))
        cell = cell * float(np.sqrt(pairs / max(p.sample_min_pairs, 1)))
        if cell <= p.source_voxel_m:
            return self._dense_rows(source)
        from v2xlake.tasks.register.sparse import spread_sample

        return self._dense_rows(source, spread_sample(source.points, cell))

    def nearest_sq_dist(self, target: Prepared, query: np.ndarray,
                        max_dist_m: float = np.inf) -> np.ndarray:
        """Bounded by ``max_dist_m``: the grid search for a point far from the cloud would
        visit every cell in between."""
        _, d2 = target.tree.batch_nearest_neighbor_search(query, max_dist_m=max_dist_m)
        return np.asarray(d2, dtype=np.float64)

    def _align_rows(self, target: Prepared, source: Prepared, rows: np.ndarray,
                    init: np.ndarray, dense: bool = False) -> SparseOutcome:
        from v2xlake.tasks.register.sparse import DenserSide, align_sparse

        p = self.params
        surf = source.handle
        surf.ensure(source.points, source.tree, rows, p.num_neighbors, p.num_threads)
        denser = (DenserSide(source.points, source.tree, surf, source.covisible_with)
                  if source.denser_side else None)
        eps = (source.translation_eps_m if source.translation_eps_m is not None
               else p.fallback_translation_eps_m if dense else None)
        return align_sparse(target.points, target.tree, target.handle, source.points[rows],
                            surf.normals[rows], surf.ratio[rows], init,
                            num_neighbors=p.num_neighbors,
                            max_correspondence_m=p.max_correspondence_m,
                            max_iterations=source.max_iterations or p.max_iterations,
                            num_threads=p.num_threads,
                            t_covisible_with=target.covisible_with, denser=denser,
                            **({"translation_eps_m": eps} if eps is not None else {}))

    def _dense_rows(self, source: Prepared, rows: np.ndarray | None = None) -> np.ndarray:
        """``rows`` (default: every source centroid), less those the other LiDAR cannot see
        where the sample was cut the same way (:meth:`prepare_covisible`)."""
        from v2xlake.tasks.register.covisible import covisible_rows

        p = self.params
        if rows is None:
            rows = np.arange(len(source.points), dtype=np.int64)
        if source.covisible_with is None:
            return rows
        surf = source.handle
        surf.ensure(source.points, source.tree, rows, p.num_neighbors, p.num_threads)
        return rows[covisible_rows(source.points, surf.normals, surf.ratio, rows,
                                   source.covisible_with)]

    def prepare_covisible(self, pts: np.ndarray, other_origin: np.ndarray, min_keep: int,
                          base: Prepared | None = None, *, as_target: bool = False
                          ) -> Prepared:
        """Co-visibility decided only where it is used: on the source sample now (its
        surfaces are needed anyway), on the target's points as they become correspondences.
        The 30 % / ``min_keep`` fallback to the whole scan is judged on the sample.

        With ``base`` (``pts`` prepared whole) the result shares its grid and its lazily
        filled surfaces: a scan registered against two agents, or also used by its agent's
        odometry, computes each point's surface once (surfaces depend on the points only).

        ``as_target``: a target's sample is never aligned, only the fallback decision reads
        it, so the co-visible fraction is estimated on ``covisible_target_rows`` of its
        sample's rows, evenly strided (each needs its surface, a k-nearest-neighbour search:
        deciding on the whole sample was a sixth of a cross pair's such searches); the
        returned sample is then the whole scan's."""
        from dataclasses import replace

        prep = base if base is not None else self.prepare_points(pts)
        rows = prep.rows()
        if not len(rows):
            return prep
        m = self.params.covisible_target_rows
        if as_target and m and len(rows) > m:
            rows = rows[::-(-len(rows) // m)]
        n, r = len(prep.points), len(rows)
        limit = max(min_keep, 0.3 * n)  # fewer co-visible (scaled to the scan): whole scan
        origin = np.asarray(other_origin, dtype=np.float64).reshape(3)
        step = r if not as_target else max(256, r // 8)
        kept: list[np.ndarray] = []
        n_kept = 0
        for a in range(0, r, step):
            part = rows[a:a + step]
            keep = self._covisible(prep, part, origin)
            kept.append(part[keep])
            n_kept += int(keep.sum())
            left = r - a - len(part)
            if as_target and (n_kept * n / r >= limit or (n_kept + left) * n / r < limit):
                break
        if n_kept * n / r < limit:  # with every row done: the decision on the whole sample
            return prep
        return replace(prep, sample=prep.sample if as_target else np.concatenate(kept),
                       covisible_with=origin)

    def _covisible(self, prep: Prepared, rows: np.ndarray, origin: np.ndarray) -> np.ndarray:
        """Which of ``rows`` the LiDAR at ``origin`` sees from the same side (their surfaces
        computed first)."""
        from v2xlake.tasks.register.covisible import covisible_rows

        p = self.params
        surf = prep.handle
        surf.ensure(prep.points, prep.tree, rows, p.num_neighbors, p.num_threads)
        return covisible_rows(prep.points, surf.normals, surf.ratio, rows, origin)


def make_backend(name: BackendName,
                 params: GicpSection = DEFAULT_GICP) -> RegistrationBackend:
    if name == "small_gicp":
        return SmallGicpBackend(params)
    if name == "open3d":
        return Open3dBackend(params)
    if name == "sparse":
        return SparseGicpBackend(params)
    raise ValueError(f"unknown registration backend {name!r} (small_gicp | open3d | sparse)")
