"""GICP backends behind one interface (main paper eq. 1b: T_init -> GICP -> T_refine).

Two implementations of Generalized-ICP [Segal et al.]: small_gicp (default: fastest here,
see tests/bench/bench_register.py) and Open3D. Each cloud is prepared ONCE (voxel
downsampling, per-point covariances, k-d tree) and reused: the reference agent's scan is
the target of every other agent's scan in the same frame, and small_gicp's one-call
``align`` on NumPy arrays would redo that work every time (60-75 % of its cost).
Both report the same quality figures, computed the same way (nearest neighbour of each
transformed source point in the target within a distance), so thresholds mean the same
whichever backend ran.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal, Protocol

import numpy as np

from v2xlake.tasks.register.voxel import voxel_downsample

BackendName = Literal["small_gicp", "open3d"]


@dataclass(frozen=True)
class GicpParams:
    """Target (reference scan) voxel finer than source voxel: the target gives the surfaces
    correspondences land on, the source only needs enough well-spread points; per-point
    covariance estimation (~2 us/point) dominates the cost, so this split is what brings
    a 225k-point pair under 0.1 s on one core (bench_register.py)."""

    voxel_m: float = 0.6  # target
    source_voxel_m: float = 1.0
    max_range_m: float = 80.0  # far returns are sparse and noisy; cropping also saves time
    num_neighbors: int = 10  # covariance estimation
    max_correspondence_m: float = 1.0
    max_iterations: int = 30
    num_threads: int = 1


@dataclass
class Prepared:
    """A downsampled cloud with covariances and a search structure, backend specific."""

    points: np.ndarray  # (M, 3) float64 downsampled
    handle: Any  # backend cloud
    tree: Any  # backend search structure


@dataclass(frozen=True)
class AlignOutcome:
    T: np.ndarray  # 4x4 T_target_source
    converged: bool
    iterations: int
    H: np.ndarray | None = None  # 6x6 Gauss-Newton Hessian at the solution [rot, trans]


class RegistrationBackend(Protocol):
    name: str

    def prepare(self, xyz: np.ndarray, *, as_target: bool = True) -> Prepared: ...

    def align(self, target: Prepared, source: Prepared, init: np.ndarray) -> AlignOutcome: ...

    def nearest_sq_dist(self, target: Prepared, query: np.ndarray) -> np.ndarray: ...


def _downsample(xyz: np.ndarray, p: GicpParams, as_target: bool) -> np.ndarray:
    return voxel_downsample(xyz, p.voxel_m if as_target else p.source_voxel_m, p.max_range_m)


class SmallGicpBackend:
    name = "small_gicp"

    def __init__(self, params: GicpParams = GicpParams()) -> None:
        import small_gicp

        self._sg = small_gicp
        self.params = params

    def prepare(self, xyz: np.ndarray, *, as_target: bool = True) -> Prepared:
        sg, p = self._sg, self.params
        pts = _downsample(xyz, p, as_target)
        cloud = sg.PointCloud(pts)
        tree = sg.KdTree(cloud, num_threads=p.num_threads)
        sg.estimate_covariances(cloud, tree, p.num_neighbors, num_threads=p.num_threads)
        return Prepared(pts, cloud, tree)

    def align(self, target: Prepared, source: Prepared, init: np.ndarray) -> AlignOutcome:
        p = self.params
        r = self._sg.align(target.handle, source.handle, target.tree,
                           init_T_target_source=np.asarray(init, np.float64),
                           registration_type="GICP",
                           max_correspondence_distance=p.max_correspondence_m,
                           num_threads=p.num_threads, max_iterations=p.max_iterations)
        return AlignOutcome(np.asarray(r.T_target_source), bool(r.converged), int(r.iterations),
                            np.asarray(r.H, dtype=np.float64))

    def nearest_sq_dist(self, target: Prepared, query: np.ndarray) -> np.ndarray:
        _, d2 = target.tree.batch_nearest_neighbor_search(
            np.ascontiguousarray(query, np.float64), num_threads=self.params.num_threads)
        return np.asarray(d2, dtype=np.float64)


class Open3dBackend:
    name = "open3d"

    def __init__(self, params: GicpParams = GicpParams()) -> None:
        import open3d as o3d

        self._o3d = o3d
        self.params = params

    def prepare(self, xyz: np.ndarray, *, as_target: bool = True) -> Prepared:
        o3d, p = self._o3d, self.params
        pts = _downsample(xyz, p, as_target)
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
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
        return AlignOutcome(np.asarray(r.transformation).copy(), True, -1)

    def nearest_sq_dist(self, target: Prepared, query: np.ndarray) -> np.ndarray:
        # the same exact nearest-neighbour figure as small_gicp (SciPy k-d tree, built lazily)
        from scipy.spatial import cKDTree

        if target.tree is None:
            target.tree = cKDTree(target.points)
        d, _ = target.tree.query(query, k=1)
        return np.asarray(d, dtype=np.float64) ** 2


def make_backend(name: BackendName,
                 params: GicpParams = GicpParams()) -> RegistrationBackend:
    if name == "small_gicp":
        return SmallGicpBackend(params)
    if name == "open3d":
        return Open3dBackend(params)
    raise ValueError(f"unknown registration backend {name!r} (small_gicp | open3d)")
