"""Screened Poisson surface reconstruction (Kazhdan and Hoppe 2013), through Open3D."""

from __future__ import annotations

import warnings

import numpy as np

from neuralsurf import geometry
from neuralsurf.errors import ConfigError, ExtractionError, InputError
from neuralsurf.structures import Mesh, PointCloud

__all__ = ["MIN_POINTS", "check_spans_3d", "reconstruct_poisson", "trim_low_density"]

MIN_POINTS = 32
"""Fewest points Poisson reconstruction accepts. Below it the indicator is shaped by the octree, not by
the data: a unit sphere from 16 exact points with exact normals came out with vertex radii 0.92-1.68
(depth 6), from 64 points 0.89-1.20."""


def check_spans_3d(points: np.ndarray, what: str, tolerance: float = 1e-6) -> None:
    """Raise InputError when the points (n, 3) lie at one location, on a line or in a plane: their
    extent along the covariance's weakest axis is at most `tolerance` times the strongest one
    (float32 rounding of exactly planar data stays below 1e-6)."""
    centred = np.asarray(points, dtype=np.float64) - np.mean(points, axis=0, dtype=np.float64)
    spread = np.sqrt(np.clip(np.linalg.eigvalsh(centred.T @ centred / len(centred)), 0.0, None))[::-1]
    if not spread[0] > 0:
        raise InputError(f"{what}: all {len(centred)} points lie at one location; a surface needs points that span 3D")
    ratio = spread / spread[0]
    if ratio[1] <= tolerance or ratio[2] <= tolerance:
        shape = "on a line" if ratio[1] <= tolerance else "in a plane"
        raise InputError(
            f"{what}: the {len(centred)} points lie {shape} (standard deviations along the principal axes "
            f"{spread[0]:.3g}, {spread[1]:.3g}, {spread[2]:.3g}), so they bound no volume and the "
            f"reconstruction would be a zero-thickness sheet; pass a cloud that samples a surface around a "
            f"volume (a flat patch can be triangulated in 2D instead)"
        )


def trim_low_density(mesh: Mesh, densities: np.ndarray, quantile: float) -> Mesh:
    """The mesh without its vertices whose density lies below the `quantile` of all densities
    (and without the faces that used them); unused vertices are dropped and faces reindexed.

    Args:
        mesh: Mesh with v vertices; densities: Float[ndarray, "v"]; quantile in [0, 1).
    """
    keep = densities >= np.quantile(densities, quantile)
    faces = mesh.faces.cpu().numpy()
    faces = faces[keep[faces].all(1)]
    used = np.zeros(len(keep), dtype=bool)
    used[faces.reshape(-1)] = True
    new_index = np.cumsum(used) - 1
    colors = None if mesh.vertex_colors is None else mesh.vertex_colors[used]
    return Mesh(mesh.vertices[used], new_index[faces], colors)


def reconstruct_poisson(
    cloud: PointCloud,
    depth: int = 9,
    density_trim: float | None = None,
    scale: float = 1.1,
    linear_fit: bool = False,
    n_threads: int = -1,
    estimate_normals: bool = True,
    normal_k: int = 30,
) -> Mesh:
    """A watertight surface through an oriented point cloud, in the cloud's (world) frame.

    Solves the screened Poisson equation on an octree of `depth` levels over the cloud's bounding
    cube enlarged by `scale`, and extracts the indicator's iso-surface. The result is closed even
    where the data is not: far from the samples it bridges holes with smooth, low-density patches,
    which `density_trim` removes.

    Args:
        cloud: points (n, 3) with outward normals; missing normals are estimated by PCA of
            `normal_k` neighbours and oriented by MST (with a warning) unless
            `estimate_normals=False`.
        depth: octree depth (resolution about bounding size / 2**depth), 1..16.
        density_trim: None, or a quantile in [0, 1) of Open3D's per-vertex sample densities; the
            vertices below it (and their faces) are removed, e.g. 0.02.
        scale: ratio of the reconstruction cube to the cloud's bounding cube (>= 1).
        linear_fit: place iso-vertices by linear interpolation of the indicator.
        n_threads: worker threads, -1 for all.
    Returns:
        Mesh (float64 vertices, world frame), with vertex colours when the cloud has colours.
    Raises:
        InputError: fewer than MIN_POINTS (32) points, points on a line or in a plane, or no normals
            with estimate_normals=False.
        ConfigError: depth, scale or density_trim out of range.
        ExtractionError: Open3D returned an empty surface.
    """
    import open3d as o3d

    if not 1 <= depth <= 16:
        raise ConfigError(f"Poisson depth must lie in 1..16 (resolution 2**depth per side), got {depth}")
    if not scale >= 1:
        raise ConfigError(f"scale must be >= 1 (the reconstruction cube over the bounding cube), got {scale}")
    if density_trim is not None and not 0 <= density_trim < 1:
        raise ConfigError(f"density_trim must be a quantile in [0, 1) or None, got {density_trim}")
    if len(cloud) < MIN_POINTS:
        raise InputError(
            f"Poisson reconstruction needs at least {MIN_POINTS} points, got {len(cloud)}: fewer give a blob "
            f"shaped by the octree rather than by the data; sample the surface more densely"
        )
    check_spans_3d(cloud.points.detach().cpu().numpy(), "Poisson reconstruction")
    if not cloud.has_normals:
        if not estimate_normals:
            raise InputError(
                "Poisson reconstruction needs oriented normals, but the cloud has none and "
                "estimate_normals=False; pass cloud.with_normals(...) or estimate them with "
                "geometry.estimate_normals(cloud, orient='mst' or 'camera')"
            )
        warnings.warn(
            f"the cloud has no normals; estimating them from {normal_k} neighbours and orienting them "
            f"by MST (outward for one closed surface). For scans, orient towards the sensor instead: "
            f"geometry.estimate_normals(cloud, orient='camera', camera=...)",
            stacklevel=2,
        )
        cloud = geometry.estimate_normals(cloud, k=normal_k, orient="mst")
    # Open3D's solver rounds to float32: a cloud far from the origin for its finest cells is solved about its mean
    points = cloud.points.detach().cpu().double()
    origin = geometry.local_origin(points, float((points.max(0).values - points.min(0).values).max()) / 2**depth)
    local = PointCloud(points - origin, cloud.normals, cloud.colors)
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        result, densities = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
            local.to_open3d(), depth=depth, width=0, scale=scale, linear_fit=linear_fit, n_threads=n_threads
        )
    if len(result.triangles) == 0:
        raise ExtractionError(
            f"Poisson reconstruction of {len(cloud)} points returned no surface; check that the normals "
            f"point outward consistently and that the cloud samples a surface"
        )
    mesh = Mesh.from_open3d(result)
    mesh = Mesh(mesh.vertices + origin, mesh.faces, mesh.vertex_colors)
    if density_trim is not None:
        mesh = trim_low_density(mesh, np.asarray(densities), density_trim)
    return mesh
