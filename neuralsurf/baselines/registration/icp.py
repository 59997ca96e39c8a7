"""ICP: `register_icp` with robust kernels and an optional voxel pyramid, run on Open3D's engines
(engine="open3d", the default: its legacy `registration_icp` on the CPU, its tensor pipeline's multi-scale
ICP on CUDA) or on our own reference loop (engine="reference": float64 numpy, point-to-point by weighted
Kabsch, point-to-plane by linearised least squares, kernels as IRLS weights, nearest neighbours from a
cached k-d tree). The reference follows Open3D's iteration and stopping rule, so both reach the same
transform on the same input (tested); it also serves the one case Open3D lacks, a robust kernel with
point-to-point. `Registration` is the result record of every registration.

Every transform is a Float64[Tensor, "4 4"] that maps source points into the target's frame:
`target ~ source @ R.T + t`.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor

from neuralsurf import geometry
from neuralsurf.baselines.registration.estimation import (
    LEAST_SQUARES,
    LeastSquares,
    PointToPoint,
    apply_transform,
    check_options,
    check_transform,
    cloud_arrays,
    degenerate_plane_system,
    voxel_downsample,
)
from neuralsurf.errors import ConfigError, InputError
from neuralsurf.strategies import choose, register
from neuralsurf.structures import Mesh, PointCloud

__all__ = [
    "ICPProblem",
    "Registration",
    "TargetCloud",
    "evaluate_registration",
    "fitness_and_rmse",
    "point_to_plane_normals",
    "register_icp",
    "register_meshes",
]


@dataclass(frozen=True)
class Registration:
    """The result of a rigid registration."""

    transform: Tensor
    """Float64[Tensor, "4 4"]: rigid motion mapping source points into the target's frame."""
    fitness: float
    """Share of source points whose nearest target point lies within max_distance (0..1); for
    `register_icp`, of the clouds of the finest pyramid level (the full clouds without one), as Open3D reports it."""
    inlier_rmse: float
    """Root mean square distance of those correspondences (point to point, as in Open3D)."""
    iterations: int | None
    """ICP iterations performed (summed over pyramid levels); None where the engine does not report
    them (Open3D's legacy CPU ICP); for `register_global`, the RANSAC iteration budget."""


@dataclass
class TargetCloud:
    """A target cloud ready for ICP: points, normals (or None) and its k-d tree."""

    points: np.ndarray
    normals: np.ndarray | None
    tree: cKDTree

    @classmethod
    def build(cls, points: np.ndarray, normals: np.ndarray | None) -> TargetCloud:
        return cls(points, normals, cKDTree(points))


def _match(
    target: TargetCloud, moved: np.ndarray, max_distance: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nearest target point of each moved source point within max_distance.

    Returns source indices (m,), target indices (m,) and distances (m,) of the m matched points.
    """
    distance, index = target.tree.query(moved, k=1, distance_upper_bound=max_distance, workers=-1)
    matched = np.flatnonzero(np.isfinite(distance))
    return matched, index[matched], distance[matched]


def _too_far(max_distance: float, n_source: int) -> InputError:
    return InputError(
        f"ICP found no correspondences: none of the {n_source} source points has a target point within "
        f"max_distance={max_distance:g} after applying init; the clouds are too far apart for this "
        f"max_distance. Give a better init (e.g. from register_global), a larger max_distance, or a "
        f"voxel pyramid (voxel_sizes)"
    )


def _icp(
    source: np.ndarray,
    target: TargetCloud,
    init: np.ndarray,
    max_distance: float,
    method: PointToPoint,
    kernel: LeastSquares,
    kernel_scale: float | None,
    max_iterations: int,
    relative_fitness: float,
    relative_rmse: float,
) -> tuple[np.ndarray, float, float, int]:
    """ICP at one resolution (Open3D's loop). Returns (transform (4, 4), fitness, rmse, iterations)."""
    transform = init
    moved = apply_transform(source, transform)
    src, tgt, dist = _match(target, moved, max_distance)
    if len(src) == 0:
        raise _too_far(max_distance, len(source))
    fitness, rmse = len(src) / len(source), float(np.sqrt(np.mean(dist**2)))
    iterations = 0
    for iterations in range(1, max_iterations + 1):
        p, q = moved[src], target.points[tgt]
        normals = target.normals[tgt] if method.needs_normals else None
        weights = kernel.weights(method.residuals(p, q, normals, dist), kernel_scale)
        if not weights.sum() > 0:
            raise InputError(
                f"every correspondence has a residual above kernel_scale={kernel_scale:g}, so the "
                f"{kernel.name} kernel gives them all zero weight; increase kernel_scale"
            )
        update = method.update(p, q, normals, weights)
        transform = update @ transform
        moved = apply_transform(source, transform)
        src, tgt, dist = _match(target, moved, max_distance)
        if len(src) == 0:
            raise _too_far(max_distance, len(source))
        previous = fitness, rmse
        fitness, rmse = len(src) / len(source), float(np.sqrt(np.mean(dist**2)))
        if abs(previous[0] - fitness) < relative_fitness and abs(previous[1] - rmse) < relative_rmse:
            break
    return transform, fitness, rmse, iterations


def _require_estimation(estimate: bool) -> None:
    """InputError for a target without normals when their estimation is off."""
    if not estimate:
        raise InputError(
            "method='point_to_plane' needs target normals, but the target has none and "
            "estimate_normals=False; pass target.with_normals(...), set estimate_normals=True, "
            "or use method='point_to_point'"
        )


def point_to_plane_normals(
    points: np.ndarray, normals: np.ndarray | None, estimate: bool, radius: float | None
) -> np.ndarray:
    """Target normals for point-to-plane: the given ones, or PCA estimates (30 nearest, within
    `radius` when given); InputError when absent and estimation is off."""
    if normals is not None:
        return normals
    _require_estimation(estimate)
    if len(points) < 3:
        raise InputError(
            f"point-to-plane ICP needs at least 3 target points to estimate normals, got {len(points)}"
        )
    with warnings.catch_warnings():  # isolated points falling back to 3 neighbours are fine here
        warnings.filterwarnings("ignore", message=".*fewer than 3 neighbours", category=UserWarning)
        return geometry.estimate_normals(torch.from_numpy(points), k=30, radius=radius).numpy()


def fitness_and_rmse(
    source: np.ndarray, target: TargetCloud, transform: np.ndarray, max_distance: float
) -> tuple[float, float]:
    """(fitness, inlier_rmse) of `transform` at max_distance."""
    src, _, dist = _match(target, apply_transform(source, transform), max_distance)
    return len(src) / len(source), float(np.sqrt(np.mean(dist**2))) if len(src) else 0.0


def evaluate_registration(
    source: PointCloud | Tensor, target: PointCloud | Tensor, transform: Tensor | np.ndarray, max_distance: float
) -> tuple[float, float]:
    """(fitness, inlier_rmse) of a rigid `transform` (4x4, source to target) on the full clouds at
    `max_distance`, as `Registration` defines them; `register_icp` reports them on its finest level."""
    check_options("point_to_point", None, None, max_distance, 1)
    source_points, _ = cloud_arrays(source, "source")
    target_points, _ = cloud_arrays(target, "target")
    transform = check_transform(transform, "transform")
    return fitness_and_rmse(source_points, TargetCloud.build(target_points, None), transform, max_distance)


def register_icp(
    source: PointCloud | Tensor,
    target: PointCloud | Tensor,
    max_distance: float,
    init: Tensor | np.ndarray | None = None,
    method: str = "point_to_point",
    kernel: str | None = None,
    kernel_scale: float | None = None,
    max_iterations: int = 50,
    relative_fitness: float = 1e-6,
    relative_rmse: float = 1e-6,
    voxel_sizes: Sequence[float] | None = None,
    estimate_normals: bool = True,
    engine: str = "open3d",
    device: str = "auto",
) -> Registration:
    """Align `source` to `target` by iterative closest points.

    Each iteration matches every moved source point to its nearest target point within
    `max_distance`, weights the matches by the robust kernel (IRLS), and solves for the rigid
    update in closed form (point-to-point: weighted Kabsch) or by one linearised least-squares step
    (point-to-plane: minimises the distance to the target's tangent planes; exact rotation from the
    axis-angle solution). It stops after `max_iterations`, or when fitness changes by less than
    `relative_fitness` and inlier RMSE by less than `relative_rmse` between iterations (absolute
    changes, as in Open3D).

    Args:
        source: PointCloud or Float[Tensor, "n 3"], moved onto the target.
        target: PointCloud or Float[Tensor, "m 3"]; point-to-plane uses its normals (signs do not
            matter), estimated from 30 neighbours when absent and `estimate_normals`.
        max_distance: largest correspondence distance, in the clouds' units (at the finest level).
        init: 4x4 rigid initial guess of the source-to-target transform; identity by default.
        method: "point_to_point" or "point_to_plane" (the "ICP method" strategies of `neuralsurf.strategies`:
            PointToPoint, PointToPlane), or an object of one's own with their methods.
        kernel: None (least squares), "huber" or "tukey" (LeastSquares, Huber, Tukey); `kernel_scale` is its
            threshold.
        voxel_sizes: optional coarse-to-fine pyramid, e.g. (4v, 2v, v): level s runs on both clouds
            downsampled to voxels of size s (centroids) with max_distance * s / voxel_sizes[-1],
            and `max_iterations` per level. Normals are then re-estimated per level within 2 s
            (or the given ones averaged per voxel).
        estimate_normals: estimate missing target normals for point-to-plane, else raise.
        engine: "open3d" (default): Open3D's ICP, the same loop compiled (robust point-to-point,
            which Open3D lacks, runs on the reference); "reference": our numpy loop; or a function
            engine(ICPProblem) -> (transform, fitness, inlier_rmse, iterations), the engines' interface.
        device: "auto", "cpu" or "cuda", for engine="open3d": "cuda" runs Open3D's tensor pipeline
            (multi-scale ICP) on the GPU and needs an Open3D built with CUDA; "auto" takes it when
            there is one, else the CPU (Open3D's legacy ICP, the fastest there).
    Returns:
        Registration; fitness and inlier_rmse at the final transform and `max_distance`, on the clouds of the
        finest level (the full clouds without `voxel_sizes`), as Open3D's pipelines report them (evaluating the
        full clouds as well made it 1.7x Open3D's time on real scans; `evaluate_registration` does it on request).
    Raises:
        InputError: empty clouds, a non-rigid init, no correspondence within max_distance, missing
            target normals with estimate_normals=False, or a degenerate point-to-plane system.
        ConfigError: unknown method, kernel, engine or device, a kernel without kernel_scale, bad
            distances, device="cuda" without CUDA in Open3D.
    """
    method, kernel = check_options(method, kernel, kernel_scale, max_distance, max_iterations)
    run = choose("ICP engine", engine)
    source_points, _ = cloud_arrays(source, "source")
    target_points, target_normals = cloud_arrays(target, "target")
    transform = check_transform(init)
    levels = list(voxel_sizes) if voxel_sizes is not None else [None]
    if voxel_sizes is not None and (not levels or not all(np.isfinite(s) and s > 0 for s in levels)):
        raise ConfigError(
            f"voxel_sizes must be positive sizes, coarse to fine, e.g. (4v, 2v, v); got {voxel_sizes}"
        )
    problem = ICPProblem(source_points, target_points, target_normals, transform, levels, max_distance, method,
                         kernel, kernel_scale, max_iterations, relative_fitness, relative_rmse, estimate_normals,
                         _open3d_device(device))
    transform, fitness, rmse, iterations = run(problem)
    return Registration(torch.from_numpy(transform), fitness, rmse, iterations)


def register_meshes(source: Mesh, target: Mesh, n_points: int = 20_000, seed: int = 0,
                    max_distance_fraction: float = 0.02, max_iterations: int = 50) -> Registration:
    """The rigid motion of `source` onto `target` (meshes in different frames, not too different in pose):
    the centre of source's bounding box moved onto target's, then point-to-plane `register_icp` of
    `n_points` surface samples of each, coarse to fine (voxels of 4, 2 and 1 % of target's longest side,
    correspondences within `max_distance_fraction` of it at the finest level, twice and four times that
    at the coarser ones). `seed` draws the samples. Returns the whole motion (centring included)."""
    generator = torch.Generator().manual_seed(seed)
    clouds = [PointCloud(*geometry.sample_mesh_surface(mesh, n_points, generator)) for mesh in (source, target)]
    (source_lo, source_hi), (lo, hi) = source.vertices.double().aminmax(dim=0), target.vertices.double().aminmax(dim=0)
    size = float((hi - lo).max())
    init = torch.eye(4, dtype=torch.float64)
    init[:3, 3] = ((lo + hi) - (source_lo + source_hi)).cpu() / 2
    voxel = max_distance_fraction * size / 2
    return register_icp(clouds[0], clouds[1], max_distance=max_distance_fraction * size, init=init,
                        method="point_to_plane", voxel_sizes=(4 * voxel, 2 * voxel, voxel),
                        max_iterations=max_iterations)


@dataclass
class ICPProblem:
    """`register_icp`'s checked input, which every ICP engine takes: `engine(problem) -> (transform (4, 4),
    fitness, inlier_rmse, iterations or None)`, the fitness and RMSE on the finest level's clouds."""

    source: np.ndarray
    """Float64[ndarray, "n 3"] source points."""
    target: np.ndarray
    """Float64[ndarray, "m 3"] target points."""
    target_normals: np.ndarray | None
    """Float64[ndarray, "m 3"] target normals, or None."""
    init: np.ndarray
    """Float64[ndarray, "4 4"] rigid initial transform."""
    levels: list
    """[None] (the full clouds) or voxel sizes, coarse to fine."""
    max_distance: float
    method: PointToPoint
    """The ICP method strategy ("ICP method" family)."""
    kernel: LeastSquares
    """The robust kernel strategy (LEAST_SQUARES for none)."""
    kernel_scale: float | None
    max_iterations: int
    relative_fitness: float
    relative_rmse: float
    estimate_normals: bool
    device: str
    """Open3D's device: "cpu" or "cuda"."""


def _open3d_device(device: str) -> str:
    """"cpu" or "cuda" for Open3D's ICP, from "auto", "cpu" or "cuda"."""
    if device not in ("auto", "cpu", "cuda"):
        raise ConfigError(f"device must be 'auto', 'cpu' or 'cuda', got {device!r}")
    if device == "cpu":
        return "cpu"
    import open3d as o3d

    has_cuda = o3d.core.cuda.is_available()
    if device == "cuda" and not has_cuda:
        raise ConfigError(
            "device='cuda' needs Open3D built with CUDA and a GPU (open3d.core.cuda.is_available() is False); "
            "use device='cpu' or 'auto'"
        )
    return "cuda" if has_cuda else "cpu"


@register("ICP engine", "reference")
def _icp_reference(problem: ICPProblem) -> tuple[np.ndarray, float, float, int]:
    """register_icp on our numpy loop."""
    p = problem
    source_points, target_points, target_normals, levels = p.source, p.target, p.target_normals, p.levels
    transform, max_distance, method = p.init, p.max_distance, p.method
    iterations = 0
    for size in levels:
        if size is None:
            src, tgt, distance = source_points, TargetCloud.build(target_points, target_normals), max_distance
        else:
            src = voxel_downsample(source_points, None, size)[0]
            tgt = TargetCloud.build(*voxel_downsample(target_points, target_normals, size))
            distance = max_distance * size / levels[-1]
        if method.needs_normals:
            tgt.normals = point_to_plane_normals(
                tgt.points, tgt.normals, p.estimate_normals, None if size is None else 2 * size
            )
        transform, _, _, done = _icp(
            src, tgt, transform, distance, method, p.kernel, p.kernel_scale, p.max_iterations, p.relative_fitness,
            p.relative_rmse,
        )
        iterations += done
    fitness, rmse = fitness_and_rmse(src, tgt, transform, max_distance)  # the finest level
    return transform, fitness, rmse, iterations


def _check_plane_system(points: np.ndarray, normals: np.ndarray) -> None:
    """InputError when the point-to-plane normal equations of the whole target are singular (one
    plane, ...): then those of any subset of its points are too."""
    jacobian = np.concatenate([np.cross(points - points.mean(0), normals), normals], axis=1)
    eigenvalues = np.linalg.eigvalsh(jacobian.T @ jacobian)
    if not eigenvalues[0] > 1e-12 * max(eigenvalues[-1], 1e-300):
        raise degenerate_plane_system()


@register("ICP engine", "open3d")
def _icp_open3d(problem: ICPProblem) -> tuple[np.ndarray, float, float, int | None]:
    """register_icp on Open3D: its tensor pipeline on CUDA, its legacy ICP on the CPU; our reference
    loop for robust point-to-point, which Open3D lacks."""
    if not problem.method.needs_normals and problem.kernel is not LEAST_SQUARES:
        return _icp_reference(problem)
    return (_icp_open3d_tensor if problem.device == "cuda" else _icp_open3d_legacy)(problem)


def _icp_open3d_legacy(problem: ICPProblem) -> tuple[np.ndarray, float, float, None]:
    """register_icp on Open3D's legacy registration_icp (CPU), level by level on Open3D's voxel
    centroids (normals given and averaged per voxel, or estimated as the reference does); each level is
    downsampled from the next finer one, the finest from the full clouds (about a third of the time of
    downsampling the full clouds at every level, and the same finest level). Open3D does not report
    its iterations: None."""
    import open3d as o3d

    p = problem
    source_points, target_points, target_normals, levels = p.source, p.target, p.target_normals, p.levels
    transform, max_distance, method = p.init, p.max_distance, p.method
    registration = o3d.pipelines.registration
    estimation = method.open3d(p.kernel, p.kernel_scale)
    criteria = registration.ICPConvergenceCriteria(p.relative_fitness, p.relative_rmse, p.max_iterations)
    clouds = {None: (_open3d_cloud(source_points), _open3d_cloud(target_points, target_normals))}
    finer = clouds[None]
    for size in sorted({size for size in levels if size is not None}):  # fine to coarse
        finer = clouds[size] = (finer[0].voxel_down_sample(size), finer[1].voxel_down_sample(size))
    for level, size in enumerate(levels):
        src, tgt = clouds[size]
        distance = max_distance if size is None else max_distance * size / levels[-1]
        if method.needs_normals:
            if tgt.has_normals():
                tgt.normalize_normals()  # voxel averages
            else:
                normals = point_to_plane_normals(np.asarray(tgt.points), None, p.estimate_normals, size and 2 * size)
                tgt.normals = o3d.utility.Vector3dVector(normals)
            if level == 0:  # the coarsest system: singular there, singular everywhere in practice
                _check_plane_system(np.asarray(tgt.points), np.asarray(tgt.normals))
        result = registration.registration_icp(src, tgt, distance, transform, estimation, criteria)
        if result.fitness == 0:
            raise _too_far(distance, len(src.points))
        transform = np.asarray(result.transformation).copy()
    return transform, float(result.fitness), float(result.inlier_rmse), None  # at the final transform


def _open3d_cloud(points: np.ndarray, normals: np.ndarray | None = None):
    """A legacy Open3D PointCloud of float64 (n, 3) points and normals."""
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    if normals is not None:
        cloud.normals = o3d.utility.Vector3dVector(normals)
    return cloud


def _icp_open3d_tensor(problem: ICPProblem, device: str = "CUDA:0") -> tuple[np.ndarray, float, float, int]:
    """register_icp on Open3D's tensor pipeline (multi_scale_icp with Open3D's own voxel pyramid and
    normals averaged per voxel; plain icp without a pyramid), on `device` (CUDA:0; CPU:0 works too)."""
    import open3d as o3d
    import open3d.core as o3c

    p = problem
    source_points, target_points, target_normals, levels = p.source, p.target, p.target_normals, p.levels
    transform, max_distance, method = p.init, p.max_distance, p.method
    relative_fitness, relative_rmse, max_iterations = p.relative_fitness, p.relative_rmse, p.max_iterations

    registration, where = o3d.t.pipelines.registration, o3c.Device(device)

    def cloud(points, normals=None):
        tensor = o3d.t.geometry.PointCloud(o3c.Tensor(points, device=where))
        if normals is not None:
            tensor.point.normals = o3c.Tensor(normals, device=where)
        return tensor

    if method.needs_normals:
        target_normals = point_to_plane_normals(target_points, target_normals, p.estimate_normals, None)
        _check_plane_system(target_points, target_normals)
    source, target = cloud(source_points), cloud(target_points, target_normals)
    estimation = method.open3d_tensor(p.kernel, p.kernel_scale)
    init = o3c.Tensor(transform)
    if levels[0] is None:
        criteria = registration.ICPConvergenceCriteria(relative_fitness, relative_rmse, max_iterations)
        result = registration.icp(source, target, max_distance, init, estimation, criteria)
    else:
        criteria = [registration.ICPConvergenceCriteria(relative_fitness, relative_rmse, max_iterations)] * len(levels)
        distances = [max_distance * size / levels[-1] for size in levels]
        result = registration.multi_scale_icp(
            source, target, o3d.utility.DoubleVector(levels), criteria, o3d.utility.DoubleVector(distances), init,
            estimation,
        )
    transform = result.transformation.cpu().numpy().astype(np.float64)
    if levels[0] is not None:  # evaluate on the finest level's clouds
        source, target = source.voxel_down_sample(levels[-1]), target.voxel_down_sample(levels[-1])
    final = registration.evaluate_registration(source, target, max_distance, o3c.Tensor(transform, device=where))
    if final.fitness == 0:
        raise _too_far(max_distance, len(source_points))
    return transform, float(final.fitness), float(final.inlier_rmse), int(result.num_iterations)
