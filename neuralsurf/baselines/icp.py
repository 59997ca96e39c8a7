"""Rigid registration of point clouds: ICP, global registration and multiway registration.

- `register_icp`: ICP with robust kernels and an optional voxel pyramid, run on Open3D's engines
  (engine="open3d", the default: its legacy `registration_icp` on the CPU, its tensor pipeline's
  multi-scale ICP on CUDA) or on our own reference loop (engine="reference": float64 numpy,
  point-to-point by weighted Kabsch, point-to-plane by linearised least squares, kernels as IRLS
  weights, nearest neighbours from a cached k-d tree). The reference follows Open3D's iteration and
  stopping rule, so both reach the same transform on the same input (tested); it also serves the
  one case Open3D lacks, a robust kernel with point-to-point.
- `register_global`: FPFH features (Open3D) matched and sampled by our own seeded RANSAC, so that
  runs repeat bit for bit; refine its result with `register_icp`.
- `register_multiway`: pairwise ICP edges in a pose graph optimised by Open3D's
  Levenberg-Marquardt.

Every transform is a Float64[Tensor, "4 4"] that maps source points into the target's frame:
`target ~ source @ R.T + t`.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor

from neuralsurf import geometry
from neuralsurf.errors import ConfigError, InputError
from neuralsurf.progress import progress_bar
from neuralsurf.strategies import choose, register
from neuralsurf.structures import Mesh, PointCloud

__all__ = [
    "Registration",
    "evaluate_registration",
    "kabsch",
    "match_features",
    "point_to_plane_step",
    "ransac_rigid",
    "register_global",
    "register_icp",
    "register_multiway",
    "voxel_downsample",
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


# ----------------------------------------------------------------------------- input checks


def _cloud_arrays(cloud: PointCloud | Tensor, name: str) -> tuple[np.ndarray, np.ndarray | None]:
    """Points (n, 3) and normals (n, 3) or None as float64 numpy arrays, checked non-empty."""
    if isinstance(cloud, PointCloud):
        points, normals = cloud.points, cloud.normals
    else:
        points, normals = torch.as_tensor(cloud), None
        if points.ndim != 2 or points.shape[1] != 3:
            raise InputError(
                f"{name} must be a PointCloud or an (n, 3) tensor, got shape {tuple(points.shape)}"
            )
    if len(points) == 0:
        raise InputError(f"{name} has no points; registration needs a non-empty cloud on both sides")
    # converted and checked in numpy: torch's threaded kernels stall on a busy machine
    def as_array(t: Tensor) -> np.ndarray:
        t = t.detach().cpu()
        return np.asarray((t if t.dtype in (torch.float32, torch.float64) else t.double()).numpy(), np.float64)

    points = as_array(points)
    if not np.isfinite(points).all():
        raise InputError(f"{name} contains NaN or inf coordinates; remove them before registering")
    return points, None if normals is None else as_array(normals)


def _check_transform(init, name: str = "init", tolerance: float = 1e-5) -> np.ndarray:
    """A 4x4 rigid transform as float64 numpy, its rotation projected onto SO(3) (tolerance-level
    rounding only); InputError otherwise."""
    if init is None:
        return np.eye(4)
    matrix = np.asarray(torch.as_tensor(init).detach().cpu(), dtype=np.float64)
    if matrix.shape != (4, 4) or not np.isfinite(matrix).all():
        raise InputError(
            f"{name} must be a finite 4x4 rigid transform [R t; 0 0 0 1], got shape {matrix.shape}"
            + ("" if matrix.shape != (4, 4) else " with NaN or inf")
        )
    rotation = matrix[:3, :3]
    orthogonality = np.abs(rotation.T @ rotation - np.eye(3)).max()
    determinant = np.linalg.det(rotation)
    bottom = np.abs(matrix[3] - [0, 0, 0, 1]).max()
    if orthogonality > tolerance or determinant < 0 or bottom > tolerance:
        raise InputError(
            f"{name} is not a rigid transform: |R^T R - I| = {orthogonality:.2e}, det R = {determinant:.3f}, "
            f"last row {matrix[3].tolist()}; give [R t; 0 0 0 1] with R a rotation (no scale, shear or "
            f"reflection)"
        )
    u, _, vt = np.linalg.svd(rotation)
    matrix = matrix.copy()
    matrix[:3, :3] = u @ vt
    matrix[3] = [0, 0, 0, 1]
    return matrix


def _check_options(
    method, kernel, kernel_scale: float | None, max_distance: float, max_iterations: int
) -> tuple[Any, Any]:
    """The ICP method and robust kernel strategies that `method` and `kernel` (None: least squares)
    name, after checking the options; ConfigError naming what is wrong."""
    method = choose("ICP method", method)
    kernel = LEAST_SQUARES if kernel is None else choose("robust kernel", kernel)
    if kernel is not LEAST_SQUARES and not (kernel_scale is not None and kernel_scale > 0):
        raise ConfigError(
            f"kernel={kernel.name!r} needs kernel_scale > 0 (got {kernel_scale}): the residual, in the clouds' "
            f"units, where down-weighting starts; about the noise standard deviation (Huber) or the "
            f"largest residual still trusted (Tukey)"
        )
    if not (np.isfinite(max_distance) and max_distance > 0):
        raise ConfigError(
            f"max_distance must be a positive distance in the clouds' units, got {max_distance}"
        )
    if max_iterations < 1:
        raise ConfigError(f"max_iterations must be >= 1, got {max_iterations}")
    return method, kernel


# ----------------------------------------------------------------------------- small pure pieces


def voxel_downsample(
    points: np.ndarray, normals: np.ndarray | None, voxel_size: float
) -> tuple[np.ndarray, np.ndarray | None]:
    """One point per occupied voxel: the centroid of its points (float64 numpy).

    Normals are averaged after flipping each onto the side of its voxel's first normal (so
    unoriented PCA normals do not cancel) and renormalised.

    Args:
        points: Float[ndarray, "n 3"]; normals: Float[ndarray, "n 3"] or None; voxel_size > 0.
    Returns:
        points Float[ndarray, "m 3"] and normals Float[ndarray, "m 3"] or None, m <= n.
    """
    keys = np.floor((points - points.min(0)) / voxel_size).astype(np.int64)
    span = keys.max(0) + 1
    flat = (keys[:, 0] * span[1] + keys[:, 1]) * span[2] + keys[:, 2]
    _, first, inverse = np.unique(flat, return_index=True, return_inverse=True)
    count = np.bincount(inverse).astype(np.float64)
    centroid = np.stack([np.bincount(inverse, points[:, i]) for i in range(3)], 1) / count[:, None]
    if normals is None:
        return centroid, None
    side = np.where((normals * normals[first][inverse]).sum(1) < 0, -1.0, 1.0)[:, None]
    summed = np.stack([np.bincount(inverse, (side * normals)[:, i]) for i in range(3)], 1)
    return centroid, summed / np.maximum(np.linalg.norm(summed, axis=1, keepdims=True), 1e-300)


def _transform(points: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """Float[ndarray, "n 3"] moved by a 4x4 rigid `matrix`."""
    return points @ matrix[:3, :3].T + matrix[:3, 3]


def _axis_angle_to_matrix(omega: np.ndarray) -> np.ndarray:
    """Rotation (3, 3) of axis-angle vector omega (3,) (Rodrigues), exact for any angle."""
    angle = np.linalg.norm(omega)
    k = np.array([[0, -omega[2], omega[1]], [omega[2], 0, -omega[0]], [-omega[1], omega[0], 0]])
    if angle < 1e-12:
        return np.eye(3) + k
    k /= angle
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * (k @ k)


class LeastSquares:
    """No robust kernel: every correspondence weighs 1."""

    name, open3d_name = None, "L2Loss"

    def weights(self, residuals: np.ndarray, scale: float | None) -> np.ndarray:
        """IRLS weights rho'(r) / r (n,) of absolute residuals (n,)."""
        return np.ones_like(residuals)


class Huber(LeastSquares):
    """Huber's kernel: weight 1 up to `scale`, then scale / r."""

    name, open3d_name = "huber", "HuberLoss"

    def weights(self, residuals: np.ndarray, scale: float | None) -> np.ndarray:
        return np.where(residuals <= scale, 1.0, scale / np.maximum(residuals, 1e-300))


class Tukey(LeastSquares):
    """Tukey's biweight: (1 - (r / scale)^2)^2 up to `scale`, then 0."""

    name, open3d_name = "tukey", "TukeyLoss"

    def weights(self, residuals: np.ndarray, scale: float | None) -> np.ndarray:
        return np.where(residuals <= scale, np.square(1 - np.square(residuals / scale)), 0.0)


LEAST_SQUARES = LeastSquares()
"""kernel=None: plain least squares."""
register("robust kernel", "huber")(Huber())
register("robust kernel", "tukey")(Tukey())


def kabsch(source: np.ndarray, target: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Weighted least-squares rigid motion (..., 4, 4) taking source (..., n, 3) onto target (..., n, 3).

    Minimises sum_i w_i |R p_i + t - q_i|^2 (Kabsch / Umeyama without scale, reflection excluded),
    independently for every leading batch index; weights are (..., n).
    """
    w = (weights / weights.sum(-1, keepdims=True))[..., None]  # (..., n, 1)
    mu_p, mu_q = (w * source).sum(-2, keepdims=True), (w * target).sum(-2, keepdims=True)  # (..., 1, 3)
    covariance = np.swapaxes(source - mu_p, -1, -2) @ ((target - mu_q) * w)  # (..., 3, 3)
    u, _, vt = np.linalg.svd(covariance)
    v, ut = np.swapaxes(vt, -1, -2), np.swapaxes(u, -1, -2)
    d = np.where(np.linalg.det(v @ ut) < 0, -1.0, 1.0)  # (...,)
    rotation = v @ (ut * np.stack([np.ones_like(d), np.ones_like(d), d], -1)[..., None])
    matrix = np.zeros((*rotation.shape[:-2], 4, 4))
    matrix[..., :3, :3] = rotation
    matrix[..., :3, 3] = (mu_q - mu_p @ np.swapaxes(rotation, -1, -2))[..., 0, :]
    matrix[..., 3, 3] = 1.0
    return matrix


def _degenerate() -> InputError:
    return InputError(
        "point-to-plane ICP is degenerate: the matched target normals do not constrain all six "
        "degrees of freedom (e.g. one plane, or too few correspondences); use "
        "method='point_to_point' or a cloud with more varied geometry"
    )


def point_to_plane_step(
    source: np.ndarray, target: np.ndarray, normals: np.ndarray, weights: np.ndarray
) -> np.ndarray:
    """One Gauss-Newton step (4, 4) of point-to-plane ICP.

    Linearises r_i = n_i . (R p_i + t - q_i) around R = I (small angles omega), solves the weighted
    6x6 normal equations for (omega, t), then builds the exact rotation exp(omega).

    Args:
        source, target, normals: Float[ndarray, "n 3"] matched points and target normals.
        weights: Float[ndarray, "n"].
    """
    residual = ((source - target) * normals).sum(1)
    jacobian = np.concatenate([np.cross(source, normals), normals], axis=1)  # (n, 6)
    weighted = jacobian * weights[:, None]
    hessian = weighted.T @ jacobian
    eigenvalues = np.linalg.eigvalsh(hessian)
    if not eigenvalues[0] > 1e-12 * max(eigenvalues[-1], 1e-300):
        raise _degenerate()
    x = -np.linalg.solve(hessian, weighted.T @ residual)
    matrix = np.eye(4)
    matrix[:3, :3], matrix[:3, 3] = _axis_angle_to_matrix(x[:3]), x[3:]
    return matrix


class PointToPoint:
    """Point-to-point ICP: the residuals are the match distances, the update a weighted Kabsch."""

    needs_normals = False

    def residuals(self, p: np.ndarray, q: np.ndarray, normals: np.ndarray | None, distances: np.ndarray):
        """Absolute residuals (n,) of matched source points p (n, 3) and target points q (n, 3)."""
        return distances

    def update(self, p: np.ndarray, q: np.ndarray, normals: np.ndarray | None, weights: np.ndarray):
        """The rigid update (4, 4) from the matches, weighted (n,)."""
        return kabsch(p, q, weights)

    def open3d(self, kernel: LeastSquares, scale: float | None):
        """Its estimation object for Open3D's legacy `registration_icp` (no robust kernel there)."""
        import open3d as o3d

        return o3d.pipelines.registration.TransformationEstimationPointToPoint()

    def open3d_tensor(self, kernel: LeastSquares, scale: float | None):
        """Its estimation object for Open3D's tensor pipeline."""
        import open3d as o3d

        return o3d.t.pipelines.registration.TransformationEstimationPointToPoint()


class PointToPlane(PointToPoint):
    """Point-to-plane ICP: residuals along the target normals, the update a linearised least-squares
    step (`point_to_plane_step`)."""

    needs_normals = True

    def residuals(self, p, q, normals, distances):
        return np.abs(((p - q) * normals).sum(1))

    def update(self, p, q, normals, weights):
        return point_to_plane_step(p, q, normals, weights)

    def open3d(self, kernel: LeastSquares, scale: float | None):
        import open3d as o3d

        registration = o3d.pipelines.registration
        robust = getattr(registration, kernel.open3d_name)(**({} if kernel.name is None else {"k": scale}))
        return registration.TransformationEstimationPointToPlane(robust)

    def open3d_tensor(self, kernel: LeastSquares, scale: float | None):
        import open3d as o3d

        robust_kernel = o3d.t.pipelines.registration.robust_kernel
        robust = robust_kernel.RobustKernel(getattr(robust_kernel.RobustKernelMethod, kernel.open3d_name),
                                            1.0 if scale is None else scale)
        return o3d.t.pipelines.registration.TransformationEstimationPointToPlane(robust)


register("ICP method", "point_to_point")(PointToPoint())
register("ICP method", "point_to_plane")(PointToPlane())


# ----------------------------------------------------------------------------- ICP


@dataclass
class _Target:
    """A target cloud ready for ICP: points, normals (or None) and its k-d tree."""

    points: np.ndarray
    normals: np.ndarray | None
    tree: cKDTree

    @classmethod
    def build(cls, points: np.ndarray, normals: np.ndarray | None) -> _Target:
        return cls(points, normals, cKDTree(points))


def _match(
    target: _Target, moved: np.ndarray, max_distance: float
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
    target: _Target,
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
    moved = _transform(source, transform)
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
        moved = _transform(source, transform)
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


def _target_normals(
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


def _evaluate(
    source: np.ndarray, target: _Target, transform: np.ndarray, max_distance: float
) -> tuple[float, float]:
    """(fitness, inlier_rmse) of `transform` at max_distance."""
    src, _, dist = _match(target, _transform(source, transform), max_distance)
    return len(src) / len(source), float(np.sqrt(np.mean(dist**2))) if len(src) else 0.0


def evaluate_registration(
    source: PointCloud | Tensor, target: PointCloud | Tensor, transform: Tensor | np.ndarray, max_distance: float
) -> tuple[float, float]:
    """(fitness, inlier_rmse) of a rigid `transform` (4x4, source to target) on the full clouds at
    `max_distance`, as `Registration` defines them; `register_icp` reports them on its finest level."""
    _check_options("point_to_point", None, None, max_distance, 1)
    source_points, _ = _cloud_arrays(source, "source")
    target_points, _ = _cloud_arrays(target, "target")
    transform = _check_transform(transform, "transform")
    return _evaluate(source_points, _Target.build(target_points, None), transform, max_distance)


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
    method, kernel = _check_options(method, kernel, kernel_scale, max_distance, max_iterations)
    run = choose("ICP engine", engine)
    source_points, _ = _cloud_arrays(source, "source")
    target_points, target_normals = _cloud_arrays(target, "target")
    transform = _check_transform(init)
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
            src, tgt, distance = source_points, _Target.build(target_points, target_normals), max_distance
        else:
            src = voxel_downsample(source_points, None, size)[0]
            tgt = _Target.build(*voxel_downsample(target_points, target_normals, size))
            distance = max_distance * size / levels[-1]
        if method.needs_normals:
            tgt.normals = _target_normals(
                tgt.points, tgt.normals, p.estimate_normals, None if size is None else 2 * size
            )
        transform, _, _, done = _icp(
            src, tgt, transform, distance, method, p.kernel, p.kernel_scale, p.max_iterations, p.relative_fitness,
            p.relative_rmse,
        )
        iterations += done
    fitness, rmse = _evaluate(src, tgt, transform, max_distance)  # the finest level
    return transform, fitness, rmse, iterations


def _check_plane_system(points: np.ndarray, normals: np.ndarray) -> None:
    """InputError when the point-to-plane normal equations of the whole target are singular (one
    plane, ...): then those of any subset of its points are too."""
    jacobian = np.concatenate([np.cross(points - points.mean(0), normals), normals], axis=1)
    eigenvalues = np.linalg.eigvalsh(jacobian.T @ jacobian)
    if not eigenvalues[0] > 1e-12 * max(eigenvalues[-1], 1e-300):
        raise _degenerate()


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
                normals = _target_normals(np.asarray(tgt.points), None, p.estimate_normals, size and 2 * size)
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
        target_normals = _target_normals(target_points, target_normals, p.estimate_normals, None)
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


# ----------------------------------------------------------------------------- global


def _fpfh(points: np.ndarray, voxel_size: float) -> tuple[np.ndarray, np.ndarray]:
    """Points (m, 3) downsampled to `voxel_size` (Open3D) and their FPFH features (m, 33)."""
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)).voxel_down_sample(voxel_size)
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel_size, max_nn=30))
    features = o3d.pipelines.registration.compute_fpfh_feature(
        cloud, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel_size, max_nn=100)
    )
    return np.asarray(cloud.points), np.asarray(features.data).T.copy()


def match_features(source: np.ndarray, target: np.ndarray, mutual: bool = True) -> np.ndarray:
    """Index pairs (k, 2) of nearest neighbours in feature space from source (m, d) to target (n, d);
    with `mutual`, only pairs that are each other's nearest neighbour (all pairs when fewer than 3)."""
    forward = cKDTree(target).query(source, k=1, workers=-1)[1]
    pairs = np.stack([np.arange(len(source)), forward], 1)
    if mutual:
        backward = cKDTree(source).query(target, k=1, workers=-1)[1]
        kept = pairs[backward[forward] == pairs[:, 0]]
        pairs = kept if len(kept) >= 3 else pairs
    return pairs


def ransac_rigid(
    source: np.ndarray,
    target: np.ndarray,
    max_distance: float,
    rng: np.random.Generator,
    max_iterations: int = 100_000,
    confidence: float = 0.999,
    sample_size: int = 3,
    edge_ratio: float = 0.9,
    batch: int = 512,
) -> tuple[np.ndarray, np.ndarray]:
    """Rigid motion (4, 4) that brings the most putative matches source[i] -> target[i] (k, 3) within
    `max_distance`, and those inliers' mask (k,).

    Hypotheses are Kabsch fits to `sample_size` random matches, drawn `batch` at a time; a sample
    is kept only when its pairwise edge lengths agree between the clouds (ratio >= `edge_ratio`)
    and its own matches land within `max_distance`. Sampling stops after `max_iterations`, or once
    the best inlier share w makes (1 - w^sample_size)^iterations <= 1 - confidence. The winner is
    refit by Kabsch on all its inliers. Deterministic for a given `rng` state.
    """
    count = len(source)
    best, best_inliers, iterations, needed = np.eye(4), np.zeros(count, dtype=bool), 0, max_iterations
    ones = np.ones((batch, sample_size))
    pairs = np.triu_indices(sample_size, 1)
    while iterations < min(needed, max_iterations):
        picks = rng.integers(0, count, size=(batch, sample_size))
        iterations += batch
        p, q = source[picks], target[picks]  # (batch, s, 3)
        edges_p = np.linalg.norm(p[:, pairs[0]] - p[:, pairs[1]], axis=-1)
        edges_q = np.linalg.norm(q[:, pairs[0]] - q[:, pairs[1]], axis=-1)
        similar = np.minimum(edges_p, edges_q) >= edge_ratio * np.maximum(edges_p, edges_q)
        keep = similar.all(1) & (edges_p.min(1) > 0)
        if not keep.any():
            continue
        transforms = kabsch(p[keep], q[keep], ones[keep])  # (h, 4, 4)
        rotations, shifts = transforms[:, None, :3, :3], transforms[:, None, :3, 3]
        moved_sample = (rotations @ p[keep][..., None])[..., 0] + shifts
        fits = (np.linalg.norm(moved_sample - q[keep], axis=-1) <= max_distance).all(1)
        if not fits.any():
            continue
        moved_all = source @ np.swapaxes(transforms[fits, :3, :3], -1, -2) + transforms[fits, None, :3, 3]
        inliers = np.linalg.norm(moved_all - target, axis=-1) <= max_distance  # (h', k)
        winner = int(inliers.sum(1).argmax())
        if inliers[winner].sum() > best_inliers.sum():
            best, best_inliers = transforms[fits][winner], inliers[winner]
            share = best_inliers.mean()
            miss = 1.0 - share**sample_size
            needed = 0 if miss <= 0 else int(np.ceil(np.log(1 - confidence) / np.log(miss)))
    if best_inliers.sum() >= sample_size:
        best = kabsch(source[best_inliers], target[best_inliers], np.ones(int(best_inliers.sum())))
        best_inliers = np.linalg.norm(_transform(source, best) - target, axis=-1) <= max_distance
    return best, best_inliers


def register_global(
    source: PointCloud | Tensor,
    target: PointCloud | Tensor,
    voxel_size: float,
    max_distance: float | None = None,
    max_iterations: int = 100_000,
    confidence: float = 0.999,
    ransac_n: int = 3,
    mutual_filter: bool = True,
    seed: int = 0,
) -> Registration:
    """Initial alignment from scratch (any rotation): FPFH features matched, then RANSAC.

    Both clouds are downsampled to `voxel_size` and get normals (radius 2 voxels) and FPFH
    features (radius 5 voxels), by Open3D. Features are matched by nearest neighbour (mutually,
    with `mutual_filter`), and `ransac_rigid` finds the motion that brings the most matches within
    `max_distance` (default 1.5 voxels), sampling `ransac_n` matches per hypothesis with
    numpy's generator seeded by `seed`: the same input and seed give the same transform, bit for
    bit. Refine the result with `register_icp(..., init=result.transform)`.

    Returns:
        Registration with fitness and inlier_rmse measured on the full clouds at `max_distance`;
        `iterations` is the RANSAC budget `max_iterations`.
    Raises:
        InputError: empty clouds, or no consistent matches (too few points or features).
        ConfigError: non-positive voxel_size or max_distance, confidence outside (0, 1).
    """
    if not (np.isfinite(voxel_size) and voxel_size > 0):
        raise ConfigError(f"voxel_size must be a positive length in the clouds' units, got {voxel_size}")
    max_distance = 1.5 * voxel_size if max_distance is None else max_distance
    _check_options("point_to_point", None, None, max_distance, max_iterations)
    if not 0 < confidence < 1:
        raise ConfigError(f"confidence must lie in (0, 1), got {confidence}")
    if ransac_n < 3:
        raise ConfigError(f"ransac_n must be at least 3 (a rigid motion needs 3 matches), got {ransac_n}")
    source_points, _ = _cloud_arrays(source, "source")
    target_points, target_normals = _cloud_arrays(target, "target")
    (source_down, source_features), (target_down, target_features) = (
        _fpfh(source_points, voxel_size),
        _fpfh(target_points, voxel_size),
    )
    if min(len(source_down), len(target_down)) < ransac_n:
        raise InputError(
            f"global registration needs at least ransac_n={ransac_n} points per cloud after "
            f"downsampling to voxel_size={voxel_size:g} (got {len(source_down)} and "
            f"{len(target_down)}); use a smaller voxel_size"
        )
    matches = match_features(source_features, target_features, mutual_filter)
    transform, inliers = ransac_rigid(
        source_down[matches[:, 0]], target_down[matches[:, 1]], max_distance,
        np.random.default_rng(seed), max_iterations, confidence, ransac_n,
    )
    if inliers.sum() < ransac_n:
        raise InputError(
            f"global registration found no consistent feature matches at voxel_size={voxel_size:g}; "
            f"the clouds may not overlap, or the voxel size is too coarse or fine for their detail "
            f"(try about 1/50 of the object's size)"
        )
    fitness, rmse = _evaluate(
        source_points, _Target.build(target_points, target_normals), transform, max_distance
    )
    return Registration(torch.from_numpy(transform), fitness, rmse, max_iterations)


# ----------------------------------------------------------------------------- multiway


def _check_connected(n: int, edges: list[tuple[int, int]], min_overlap: float, max_distance: float) -> None:
    """InputError unless the n scans form one connected pose graph through `edges`."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    rows, cols = np.array(edges, dtype=np.int64).reshape(-1, 2).T
    count, labels = connected_components(
        coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n)), directed=False
    )
    if count > 1:
        groups = [np.flatnonzero(labels == label).tolist() for label in range(count)]
        raise InputError(
            f"the scans split into {count} groups with no overlap of min_overlap={min_overlap:g} "
            f"(ICP fitness at max_distance={max_distance:g}) between them: {groups}; give init_poses "
            f"closer to the truth, a larger max_distance, or a smaller min_overlap"
        )


def register_multiway(
    scans: Sequence[PointCloud | Tensor],
    voxel_size: float,
    max_distance: float | None = None,
    init_poses: Sequence[Tensor] | Tensor | None = None,
    reference: int = 0,
    method: str = "point_to_plane",
    min_overlap: float = 0.3,
    max_iterations: int = 50,
    edge_prune_threshold: float = 0.25,
    progress: bool = True,
) -> list[Tensor]:
    """Poses bringing every scan into the reference scan's frame, by pose-graph optimisation.

    Every pair of scans is registered by `register_icp` on voxel-downsampled copies (pyramid
    4, 2, 1 x `voxel_size`, from the pair's relative init pose). Pairs whose overlap (ICP fitness)
    reaches `min_overlap` become edges weighted by their information matrices: odometry edges for
    successive scans, loop closures for the others. Open3D's Levenberg-Marquardt global
    optimisation then finds the poses that agree with the edges best, pruning loop closures that
    disagree (`edge_prune_threshold`).

    Args:
        scans: clouds, each in its own frame (n_i, 3); at least 2.
        voxel_size: downsampling voxel, in the scans' units.
        max_distance: correspondence distance at the finest level (default 1.5 * voxel_size).
        init_poses: optional scan-to-common-frame 4x4 poses, one per scan (identity: the scans are
            assumed roughly aligned already).
        reference: index of the scan whose frame the poses are expressed in.
        progress: a progress bar over the n (n - 1) / 2 pairwise registrations when they last more
            than a few seconds (neuralsurf.progress); False for none.
    Returns:
        one Float64[Tensor, "4 4"] per scan, mapping its points into the reference scan's frame
        (the reference's own pose is the identity).
    Raises:
        InputError: fewer than 2 scans, bad poses, or scans that split into groups with no
            overlap between them.
    """
    import open3d as o3d

    if len(scans) < 2:
        raise InputError(f"multiway registration needs at least 2 scans, got {len(scans)}")
    if not 0 <= reference < len(scans):
        raise ConfigError(f"reference must index a scan in [0, {len(scans)}), got {reference}")
    if not (np.isfinite(voxel_size) and voxel_size > 0):
        raise ConfigError(f"voxel_size must be a positive length in the scans' units, got {voxel_size}")
    max_distance = 1.5 * voxel_size if max_distance is None else max_distance
    estimation, _ = _check_options(method, None, None, max_distance, max_iterations)
    if init_poses is not None and len(init_poses) != len(scans):
        raise InputError(f"init_poses has {len(init_poses)} poses for {len(scans)} scans; give one per scan")
    poses = [
        np.eye(4) if init_poses is None else _check_transform(p, f"init_poses[{i}]")
        for i, p in enumerate(init_poses if init_poses is not None else scans)
    ]
    downsampled = []
    for i, scan in enumerate(scans):
        points, normals = voxel_downsample(*_cloud_arrays(scan, f"scans[{i}]"), voxel_size)
        if estimation.needs_normals:
            normals = _target_normals(points, normals, True, 2 * voxel_size)
        downsampled.append(
            PointCloud(torch.from_numpy(points), None if normals is None else torch.from_numpy(normals))
        )
    pipeline = o3d.pipelines.registration
    graph = pipeline.PoseGraph()
    for pose in poses:
        graph.nodes.append(pipeline.PoseGraphNode(pose))
    edges = []
    pairs = [(i, j) for i in range(len(scans)) for j in range(i + 1, len(scans))]
    for i, j in progress_bar(pairs, desc="multiway ICP", unit="pair", enabled=progress):
        relative = np.linalg.inv(poses[j]) @ poses[i]
        try:
            edge = register_icp(
                downsampled[i],
                downsampled[j],
                max_distance,
                relative,
                method,
                max_iterations=max_iterations,
                voxel_sizes=(4 * voxel_size, 2 * voxel_size, voxel_size),
            )
        except InputError:  # no overlap at all from this init
            continue
        if edge.fitness < min_overlap:
            continue
        transform = edge.transform.numpy()
        information = pipeline.get_information_matrix_from_point_clouds(
            downsampled[i].to_open3d(), downsampled[j].to_open3d(), max_distance, transform
        )
        graph.edges.append(pipeline.PoseGraphEdge(i, j, transform, information, uncertain=j != i + 1))
        edges.append((i, j))
    _check_connected(len(scans), edges, min_overlap, max_distance)
    option = pipeline.GlobalOptimizationOption(
        max_correspondence_distance=max_distance,
        edge_prune_threshold=edge_prune_threshold,
        reference_node=reference,
    )
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        pipeline.global_optimization(
            graph,
            pipeline.GlobalOptimizationLevenbergMarquardt(),
            pipeline.GlobalOptimizationConvergenceCriteria(),
            option,
        )
    to_reference = np.linalg.inv(np.asarray(graph.nodes[reference].pose))
    poses = [to_reference @ np.asarray(node.pose) for node in graph.nodes]
    poses[reference] = np.eye(4)  # exactly, not up to rounding
    return [torch.from_numpy(pose) for pose in poses]
