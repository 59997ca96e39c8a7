"""Multiway registration: pairwise ICP edges in a pose graph optimised by Open3D's Levenberg-Marquardt."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor

from neuralsurf.baselines.registration.estimation import (
    check_options,
    check_transform,
    cloud_arrays,
    voxel_downsample,
)
from neuralsurf.baselines.registration.icp import point_to_plane_normals, register_icp
from neuralsurf.errors import ConfigError, InputError
from neuralsurf.progress import progress_bar
from neuralsurf.structures import PointCloud

__all__ = ["register_multiway"]


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
    estimation, _ = check_options(method, None, None, max_distance, max_iterations)
    if init_poses is not None and len(init_poses) != len(scans):
        raise InputError(f"init_poses has {len(init_poses)} poses for {len(scans)} scans; give one per scan")
    poses = [
        np.eye(4) if init_poses is None else check_transform(p, f"init_poses[{i}]")
        for i, p in enumerate(init_poses if init_poses is not None else scans)
    ]
    downsampled = []
    for i, scan in enumerate(scans):
        points, normals = voxel_downsample(*cloud_arrays(scan, f"scans[{i}]"), voxel_size)
        if estimation.needs_normals:
            normals = point_to_plane_normals(points, normals, True, 2 * voxel_size)
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
