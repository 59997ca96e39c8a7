"""Scenes: recipes that build an input (point cloud, depth frames) and, when known, its ground truth.

One family for train.py (configs/data) and evaluate.py (configs/scene). Every recipe is
deterministic for its arguments; the heavier ones are cached per process, so all the methods of
an evaluation share one input. A recipe whose data or optional dependency is missing raises
`SceneUnavailable` (evaluate.py skips its rows; train.py stops with its message).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import torch

from neuralsurf.errors import MissingDependencyError, NeuralsurfError
from neuralsurf.geometry import cloud_from_mesh
from neuralsurf.scenes.analytic import analytic_shape
from neuralsurf.structures import DepthFrames, Mesh, PointCloud


class SceneUnavailable(NeuralsurfError):
    """A scene cannot be built here (data or optional dependency missing)."""


@dataclass(frozen=True)
class Scene:
    """An input and what it should reconstruct to, in one world frame."""

    name: str
    """Short identifier used in run directories and tables."""
    cloud: PointCloud
    """The input point cloud (with normals when the recipe provides them); for depth scenes the
    back-projection of `frames`."""
    ground_truth: Mesh | None = None
    """The true surface, for metrics; None for captures without one."""
    frames: DepthFrames | None = None
    """Depth images with cameras (depth scenes), for ray fits and TSDF fusion."""
    description: str = ""
    """One line for reports."""
    held_out: DepthFrames | None = None
    """Depth frames kept out of every method's input, to score reconstructions without ground truth."""
    depth_input: bool = False
    """True when `frames` are the input and `cloud` their back-projection (False for range scans,
    whose frames are renderings of the scanned points for TSDF fusion)."""


def data_root(root: str | Path | None = None) -> Path:
    """The folder of real captures: `root` if given, else $NEURALSURF_DATA, else ../shared/data."""
    return Path(root or os.environ.get("NEURALSURF_DATA") or "../shared/data")


def _bunny_mesh() -> Mesh:
    from neuralsurf.scenes.bunny import bunny

    try:
        return bunny()
    except MissingDependencyError as error:
        raise SceneUnavailable(str(error)) from None


def mesh_scene(mesh: Mesh, n_points: int = 100_000, noise: float = 0.0, normals: bool = True,
               seed: int = 0, name: str = "mesh") -> Scene:
    """Sample `n_points` from `mesh`; `noise` is a Gaussian standard deviation as a fraction of
    the bounding box's longest side; `normals=False` drops the normals."""
    size = float((mesh.bounds[1] - mesh.bounds[0]).max())
    cloud = cloud_from_mesh(mesh, n_points, noise=noise * size, seed=seed)
    text = f"{n_points} surface points, noise {noise:.2%} of the box, {'with' if normals else 'no'} normals"
    return Scene(name, cloud if normals else cloud.with_normals(None), mesh, description=text)


@lru_cache(maxsize=16)
def bunny_points(name: str = "bunny", n_points: int = 100_000, noise: float = 0.0, normals: bool = True,
                 seed: int = 0) -> Scene:
    """`n_points` area-uniform samples of the watertight bunny (the `data` extra), as `mesh_scene`."""
    return mesh_scene(_bunny_mesh(), n_points, noise, normals, seed, name=name)


@lru_cache(maxsize=16)
def analytic_scene(shape: str = "sphere", n_points: int = 20_000, noise: float = 0.0, normals: bool = True,
                   seed: int = 0, name: str | None = None) -> Scene:
    """Samples of an analytic shape (sphere, torus, box); the ground truth is its fine tessellation."""
    return mesh_scene(analytic_shape(shape).mesh(), n_points, noise, normals, seed, name=name or shape)


def file_scene(path: str | Path, ground_truth: str | Path | None = None, name: str | None = None) -> Scene:
    """A point cloud read from `path`, with an optional ground-truth mesh file."""
    from neuralsurf.io import read_mesh, read_point_cloud

    mesh = read_mesh(ground_truth) if ground_truth is not None else None
    return Scene(name or Path(path).stem, read_point_cloud(path), mesh, description=f"point cloud {path}")


def depth_scene(name: str, frames: DepthFrames, ground_truth: Mesh | None = None, hold_out_every: int = 0,
                cloud_stride: int = 1, description: str = "") -> Scene:
    """A scene of depth frames: every `hold_out_every`-th frame (the 10th, 20th, ... for 10; 0 = none)
    is held out for scoring, the others are the input, also back-projected into a cloud (every
    `cloud_stride`-th pixel, image-space normals) for methods that take points."""
    from neuralsurf.geometry import depth_to_cloud

    held_out = None
    if hold_out_every:
        index = torch.arange(len(frames))
        held_out, frames = frames[index[index % hold_out_every == hold_out_every - 1]], frames[
            index[index % hold_out_every != hold_out_every - 1]]
    cloud = depth_to_cloud(frames, stride=cloud_stride, with_normals=True)
    text = (f"{len(frames)} depth views {frames.width}x{frames.height}"
            + (f" (+{len(held_out)} held out)" if held_out is not None else "")
            + f", {len(cloud)} back-projected points" + (f"; {description}" if description else ""))
    return Scene(name, cloud, ground_truth, frames, text, held_out, depth_input=True)


@lru_cache(maxsize=8)
def bunny_depth(name: str = "bunny_depth", n_views: int = 24, width: int = 320, height: int = 240,
                noise: str = "kinect", seed: int = 0, stride: int = 1, hold_out_every: int = 0) -> Scene:
    """Synthetic depth views of the bunny (`scan_depth`, `noise` "none", "gaussian" or "kinect")."""
    from neuralsurf.scenes.scanner import scan_depth

    mesh = _bunny_mesh()
    frames = scan_depth(mesh, n_views=n_views, width=width, height=height, noise=noise, seed=seed)
    return depth_scene(name, frames, mesh, hold_out_every, stride, f"{noise} noise")


@lru_cache(maxsize=4)
def rgbd_scene(path: str, name: str | None = None, stride: int = 1, max_frames: int | None = None,
               hold_out_every: int = 10, cloud_stride: int = 4, ground_truth: str | None = None) -> Scene:
    """A 7-Scenes, TUM or Redwood folder (`read_rgbd_folder`, every `stride`-th frame) as a depth scene
    with every `hold_out_every`-th frame held out; an optional ground-truth mesh file."""
    from neuralsurf.io import read_mesh, read_rgbd_folder

    frames = read_rgbd_folder(path, stride=stride, max_frames=max_frames, with_color=False)
    mesh = read_mesh(ground_truth) if ground_truth else None
    return depth_scene(name or Path(path).name, frames, mesh, hold_out_every, cloud_stride, f"real RGB-D {path}")


def redkitchen(name: str = "redkitchen", root: str | None = None, folder: str = "7scenes_redkitchen_every10",
               stride: int = 1, max_frames: int | None = None, hold_out_every: int = 10, cloud_stride: int = 4) -> Scene:
    """The real 7-Scenes redkitchen frames under the data root (`data_root(root)`)."""
    path = data_root(root) / folder
    if not path.is_dir():
        raise SceneUnavailable(f"{path} not found: pass data_root=<folder holding {folder}/> or set NEURALSURF_DATA "
                               f"(the 7-Scenes redkitchen frames, see the README's data section)")
    return rgbd_scene(str(path), name, stride, max_frames, hold_out_every, cloud_stride)


@lru_cache(maxsize=4)
def stanford_scans(name: str = "stanford_scans", root: str | None = None, conf: str = "stanford_bunny/data/bun.conf",
                   ground_truth: str = "stanford_bunny/reconstruction/bun_zipper.ply") -> Scene:
    """The real range scans of the Stanford bunny, aligned by their .conf and merged into one cloud
    (normals towards the scanners), and as one depth image per scan (read_range_scan_frames) for
    TSDF fusion; ground truth: Stanford's zippered reconstruction."""
    from neuralsurf.io import read_mesh, read_range_scan_frames, read_range_scans

    conf_path, gt_path = data_root(root) / conf, data_root(root) / ground_truth
    for path in (conf_path, gt_path):
        if not path.is_file():
            raise SceneUnavailable(f"{path} not found; pass data_root=<folder holding stanford_bunny/> or set "
                                   f"NEURALSURF_DATA")
    clouds = read_range_scans(conf_path)
    points = torch.cat([c.points.double() for c in clouds])
    normals = torch.cat([c.normals.double() for c in clouds]) if all(c.has_normals for c in clouds) else None
    cloud = PointCloud(points, normals)
    text = f"{len(clouds)} real range scans aligned by {conf_path.name} ({len(cloud)} points)"
    return Scene(name, cloud, read_mesh(gt_path), read_range_scan_frames(conf_path), text)
