"""Benchmark scenes: recipes that build an input (point cloud, depth frames) and its ground truth.

Every recipe is deterministic for its arguments (seeds fixed) and cached per process, so all the
methods of a run (and repeated runs in one process) share one input.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import torch

from neuralsurf.errors import NeuralsurfError
from neuralsurf.scenes import Scene
from neuralsurf.structures import Mesh, PointCloud


class SceneUnavailable(NeuralsurfError):
    """A scene cannot be built here (data or optional dependency missing): its rows are skipped."""


def _bunny_mesh() -> Mesh:
    from neuralsurf.errors import MissingDependencyError
    from neuralsurf.scenes import bunny

    try:
        return bunny()
    except MissingDependencyError as error:
        raise SceneUnavailable(str(error)) from None


@lru_cache(maxsize=16)
def bunny_points(name: str = "bunny", n_points: int = 100_000, noise: float = 0.0, normals: bool = True,
                 seed: int = 0) -> Scene:
    """`n_points` area-uniform samples of the watertight bunny; `noise` is a Gaussian std as a fraction
    of the bounding box's longest side; `normals=False` drops the normals."""
    from neuralsurf.scenes import mesh_scene

    scene = mesh_scene(_bunny_mesh(), n_points, noise, normals, seed, name=name)
    text = f"{n_points} bunny points, noise {noise:.2%} of the box, {'with' if normals else 'no'} normals"
    return Scene(name, scene.cloud, scene.ground_truth, None, text)


@lru_cache(maxsize=16)
def analytic(name: str = "sphere", shape: str = "sphere", n_points: int = 20_000, noise: float = 0.0,
             normals: bool = True, seed: int = 0) -> Scene:
    """Samples of an analytic shape (sphere, torus, box); the ground truth is its fine tessellation."""
    from neuralsurf.scenes import analytic_scene

    scene = analytic_scene(shape, n_points, noise, normals, seed)
    text = f"{n_points} points of an analytic {shape}, noise {noise:.2%}, {'with' if normals else 'no'} normals"
    return Scene(name, scene.cloud, scene.ground_truth, None, text)


@lru_cache(maxsize=8)
def bunny_depth(name: str = "bunny_depth", n_views: int = 24, width: int = 320, height: int = 240,
                noise: str = "kinect", seed: int = 0, stride: int = 1) -> Scene:
    """Synthetic depth views of the bunny (scan_depth); point methods get the back-projected cloud
    (every `stride`-th pixel, with image-space normals)."""
    from neuralsurf.geometry import depth_to_cloud
    from neuralsurf.scenes import scan_depth

    mesh = _bunny_mesh()
    frames = scan_depth(mesh, n_views=n_views, width=width, height=height, noise=noise, seed=seed)
    cloud = depth_to_cloud(frames, stride=stride, with_normals=True)
    text = f"{n_views} depth views {width}x{height}, {noise} noise ({len(cloud)} back-projected points)"
    return Scene(name, cloud, mesh, frames, text)


@lru_cache(maxsize=4)
def stanford_scans(name: str = "stanford_scans", data_root: str = "../shared/data",
                   conf: str = "stanford_bunny/data/bun.conf",
                   ground_truth: str = "stanford_bunny/reconstruction/bun_zipper.ply") -> Scene:
    """The real range scans of the Stanford bunny, aligned by their .conf and merged into one cloud
    (normals towards the scanners), and as one depth image per scan (read_range_scan_frames) for
    TSDF fusion; ground truth: Stanford's zippered reconstruction."""
    from neuralsurf.io import read_mesh, read_range_scan_frames, read_range_scans

    root = Path(data_root)
    conf_path, gt_path = root / conf, root / ground_truth
    for path in (conf_path, gt_path):
        if not path.is_file():
            raise SceneUnavailable(f"{path} not found; pass data_root=<folder holding stanford_bunny/>")
    clouds = read_range_scans(conf_path)
    points = torch.cat([c.points.double() for c in clouds])
    normals = torch.cat([c.normals.double() for c in clouds]) if all(c.has_normals for c in clouds) else None
    cloud = PointCloud(points, normals)
    text = f"{len(clouds)} real range scans aligned by {conf_path.name} ({len(cloud)} points)"
    return Scene(name, cloud, read_mesh(gt_path), read_range_scan_frames(conf_path), text)
