"""Global registration: an initial alignment from scratch (any rotation), FPFH features (Open3D) matched
and sampled by our own seeded RANSAC, so that runs repeat bit for bit; refine its result with
`register_icp`."""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial import cKDTree
from torch import Tensor

from neuralsurf.baselines.registration.estimation import apply_transform, check_options, cloud_arrays, kabsch
from neuralsurf.baselines.registration.icp import Registration, TargetCloud, fitness_and_rmse
from neuralsurf.errors import ConfigError, InputError
from neuralsurf.structures import PointCloud

__all__ = ["fpfh_features", "match_features", "ransac_rigid", "register_global"]


def fpfh_features(points: np.ndarray, voxel_size: float) -> tuple[np.ndarray, np.ndarray]:
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
        best_inliers = np.linalg.norm(apply_transform(source, best) - target, axis=-1) <= max_distance
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
    check_options("point_to_point", None, None, max_distance, max_iterations)
    if not 0 < confidence < 1:
        raise ConfigError(f"confidence must lie in (0, 1), got {confidence}")
    if ransac_n < 3:
        raise ConfigError(f"ransac_n must be at least 3 (a rigid motion needs 3 matches), got {ransac_n}")
    source_points, _ = cloud_arrays(source, "source")
    target_points, target_normals = cloud_arrays(target, "target")
    (source_down, source_features), (target_down, target_features) = (
        fpfh_features(source_points, voxel_size),
        fpfh_features(target_points, voxel_size),
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
    fitness, rmse = fitness_and_rmse(
        source_points, TargetCloud.build(target_points, target_normals), transform, max_distance
    )
    return Registration(torch.from_numpy(transform), fitness, rmse, max_iterations)
