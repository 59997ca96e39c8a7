"""Scenes: recipes that produce an input point cloud and, when known, the ground-truth surface."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from neuralsurf.geometry import cloud_from_mesh
from neuralsurf.scenes.analytic import analytic_shape
from neuralsurf.structures import DepthFrames, Mesh, PointCloud


@dataclass(frozen=True)
class Scene:
    """An input and what it should reconstruct to, in one world frame."""

    name: str
    """Short identifier used in run directories and tables."""
    cloud: PointCloud
    """The input point cloud (with normals when the recipe provides them)."""
    ground_truth: Mesh | None = None
    """The true surface, for metrics; None for captures without one."""
    frames: DepthFrames | None = None
    """Depth images with cameras, for methods that fuse depth (TSDF); `cloud` is then their back-projection."""
    description: str = ""
    """One line for reports."""


def mesh_scene(mesh: Mesh, n_points: int = 100_000, noise: float = 0.0, normals: bool = True,
               seed: int = 0, name: str = "mesh") -> Scene:
    """Sample `n_points` from `mesh`; `noise` is a Gaussian standard deviation as a fraction of
    the bounding box's longest side; `normals=False` drops the normals."""
    size = float((mesh.bounds[1] - mesh.bounds[0]).max())
    cloud = cloud_from_mesh(mesh, n_points, noise=noise * size, seed=seed)
    return Scene(name, cloud if normals else cloud.with_normals(None), mesh)


def analytic_scene(shape: str, n_points: int = 100_000, noise: float = 0.0, normals: bool = True,
                   seed: int = 0, **parameters) -> Scene:
    """Sample an analytic shape (sphere, torus, box); the ground truth is its fine tessellation."""
    return mesh_scene(analytic_shape(shape, **parameters).mesh(), n_points, noise, normals, seed, name=shape)


def file_scene(path: str | Path, ground_truth: str | Path | None = None, name: str | None = None) -> Scene:
    """A point cloud read from `path`, with an optional ground-truth mesh file."""
    from neuralsurf.io import read_mesh, read_point_cloud

    mesh = read_mesh(ground_truth) if ground_truth is not None else None
    return Scene(name or Path(path).stem, read_point_cloud(path), mesh)
