"""What every rigid registration shares: input checks, robust kernels and transformation estimations.

- Input checks: clouds as float64 arrays, rigid 4x4 transforms, the ICP options.
- Robust kernels (`LeastSquares`, `Huber`, `Tukey`: IRLS weights) and estimations (`PointToPoint`: weighted
  Kabsch; `PointToPlane`: one linearised least-squares step), registered by name in `neuralsurf.strategies`.

Every transform maps source points into the target's frame: `target ~ source @ R.T + t`.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import Tensor

from neuralsurf.errors import ConfigError, InputError
from neuralsurf.strategies import choose, register
from neuralsurf.structures import PointCloud

__all__ = [
    "LEAST_SQUARES",
    "Huber",
    "LeastSquares",
    "PointToPlane",
    "PointToPoint",
    "Tukey",
    "apply_transform",
    "axis_angle_to_matrix",
    "check_options",
    "check_transform",
    "cloud_arrays",
    "degenerate_plane_system",
    "kabsch",
    "point_to_plane_step",
    "small_motion",
    "voxel_downsample",
]


# ----------------------------------------------------------------------------- input checks


def cloud_arrays(cloud: PointCloud | Tensor, name: str) -> tuple[np.ndarray, np.ndarray | None]:
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


def check_transform(init, name: str = "init", tolerance: float = 1e-5) -> np.ndarray:
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


def check_options(
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


def apply_transform(points: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """Float[ndarray, "n 3"] moved by a 4x4 rigid `matrix`."""
    return points @ matrix[:3, :3].T + matrix[:3, 3]


def axis_angle_to_matrix(omega: np.ndarray) -> np.ndarray:
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


def degenerate_plane_system() -> InputError:
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
    motion = small_motion(weighted.T @ jacobian, weighted.T @ residual, 1e-12)
    if motion is None:
        raise degenerate_plane_system()
    return motion


def small_motion(hessian: np.ndarray, gradient: np.ndarray, min_conditioning: float) -> np.ndarray | None:
    """The rigid motion (4, 4) [exp(omega) t; 0 1] minimising x^T hessian x / 2 + gradient^T x over x = (omega, t),
    from Gauss-Newton's normal equations: `hessian` (6, 6), `gradient` (6,); None when the hessian's smallest
    eigenvalue is not above `min_conditioning` times its largest (degenerate: fewer than six directions constrained)."""
    eigenvalues = np.linalg.eigvalsh(hessian)
    if not eigenvalues[0] > min_conditioning * max(eigenvalues[-1], 1e-300):
        return None
    x = -np.linalg.solve(hessian, gradient)
    matrix = np.eye(4)
    matrix[:3, :3], matrix[:3, 3] = axis_angle_to_matrix(x[:3]), x[3:]
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
