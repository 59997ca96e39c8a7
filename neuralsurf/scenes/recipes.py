"""Scenes: recipes that build an input (point cloud, depth frames) and, when known, its ground truth.

One family for train.py (configs/data) and evaluate.py (configs/scene). Every recipe is
deterministic for its arguments; the heavier ones are cached per process, so all the methods of
an evaluation share one input. A recipe whose data or optional dependency is missing raises
`SceneUnavailable` (evaluate.py skips its rows; train.py stops with its message).
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass, replace
from functools import lru_cache
from pathlib import Path
from typing import Any

import torch

from neuralsurf.baselines.tracking import track_frames
from neuralsurf.cameras import depth_to_cloud
from neuralsurf.data import DATASETS, cache_dir, find_folder
from neuralsurf.errors import ConfigError, MissingDependencyError, NeuralsurfError
from neuralsurf.extract import NearPointsField, extract_mesh
from neuralsurf.geometry import cloud_from_mesh, colors_from_points, isolated_points
from neuralsurf.io import (
    read_mesh,
    read_photometric,
    read_point_cloud,
    read_range_scan_frames,
    read_range_scans,
    read_rgbd_folder,
)
from neuralsurf.io.rgbd import has_poses, read_depth_frames
from neuralsurf.observations.observed import ObservedSurface, extract_observed
from neuralsurf.photometric import PhotometricStereoResult, integrate_least_squares, photometric_stereo
from neuralsurf.scenes.analytic import analytic_shape
from neuralsurf.scenes.bunny import bunny
from neuralsurf.scenes.photometric_rig import SpecularLobe, cap_lights, render_photometric
from neuralsurf.scenes.scanner import intrinsics_from_fov, look_at, orbit_cameras, scan_depth
from neuralsurf.snapping import snap_to_cloud
from neuralsurf.structures import DepthFrames, Mesh, PhotometricCapture, PointCloud


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
    photometric: tuple[PhotometricCapture, ...] | None = None
    """Photometric captures (images under known lights, with ground-truth normals where known), one per
    view; for photometric stereo methods and, with `normal_maps`, depth + normals fusion."""
    normal_maps: tuple[PhotometricStereoResult, ...] | None = None
    """The photometric stereo estimate of each capture (normals, confidence, mask) that fusion methods
    take as their input normals (NormalMaps, Nehab fusion)."""
    near_distance: float | None = None
    """Rooms: neural fields are meshed only this close to the input points (world units), so space no
    camera saw stays empty; None for objects (a mask would hollow out their insides)."""
    cloud_from_truth: bool = False
    """True when `cloud` is made from the ground truth only to complete the scene (photometric captures
    with neither depth nor a true surface): a mesh reconstructed on it is not scored (its row is skipped)."""
    trajectory: torch.Tensor | None = None
    """Float64[Tensor, "n 4 4"]: camera poses estimated by tracking (every frame, held-out ones included, in
    capture order) when the capture came without poses or they were not used; None otherwise."""


def extract_scene_mesh(field: torch.nn.Module, scene: Scene, extract: dict[str, Any] | None = None,
                       seed: int = 0) -> Mesh:
    """`extract_mesh(field, **extract)` for a world-frame field fitted to `scene`; a room (the scene's
    `near_distance`, or a `near_distance` option) is meshed only that close to its input points, or with an
    `observed_voxel` option only where its frames observed a surface (`extract_observed`, voxels of that size).
    An `onto_points` option (a share) moves the mesh onto the scene's cloud where held out points say it comes
    closer (`snapping.snap_to_cloud`, that share held out with `seed`: a point fit's own held-out points). A mesh of a
    coloured cloud takes its colours from the nearest points (`geometry.colors_from_points`)."""
    options = dict(extract or {})
    options.pop("format", None)  # the file format of train.py's mesh, not an extract_mesh argument
    voxel = options.pop("observed_voxel", None)
    share = options.pop("onto_points", None)
    near = options.pop("near_distance", None) or scene.near_distance
    if voxel and near is not None and scene.frames is not None:
        kept = {k: options[k] for k in ("resolution", "chunk_size", "level", "progress") if k in options}
        mesh = extract_observed(field, ObservedSurface.from_frames(scene.frames, voxel), **kept)
    else:
        mesh = extract_mesh(field if near is None else NearPointsField(field, scene.cloud.points, near), **options)
    mesh = snap_to_cloud(mesh, scene.cloud, share, seed) if share else mesh
    if mesh.vertex_colors is None and scene.cloud is not None and scene.cloud.colors is not None:
        mesh = Mesh(mesh.vertices, mesh.faces, colors_from_points(mesh.vertices, scene.cloud))
    return mesh


def data_root(root: str | Path | None = None) -> Path:
    """The folder of real captures: `root` if given, else $NEURALSURF_DATA, else the cache that
    `python -m neuralsurf data fetch` fills (neuralsurf.data.cache_dir())."""
    return Path(root or os.environ.get("NEURALSURF_DATA") or cache_dir()).expanduser()


def data_path(root: str | Path | None, relative: str | Path) -> Path:
    """Where `relative` (a path under a data root, e.g. "stanford_bunny/data/bun.conf") is read from:
    under `root` if given; else the first of $NEURALSURF_DATA, the fetch cache that holds it (where
    neuralsurf.data.fetch looks too); else under `data_root()`, for the message that it is missing."""
    found = None if root else find_folder(relative)
    return found[1] if found is not None else data_root(root) / relative


def scene_unavailable(path: Path, holder: str) -> SceneUnavailable:
    """The error of a scene whose data `path` is missing: the command that fetches the data set of folder
    `holder` (when neuralsurf.data has one), or point data_root at the folder holding `holder`/."""
    name = next((name for name, dataset in DATASETS.items() if dataset.folder == holder), None)
    get = f"run `python -m neuralsurf data fetch {name}`, " if name else ""
    return SceneUnavailable(f"{path} not found: {get}pass data_root=<folder holding {holder}/> or set NEURALSURF_DATA")


def _bunny_mesh() -> Mesh:
    try:
        return bunny()
    except MissingDependencyError as error:
        raise SceneUnavailable(str(error)) from None


def mesh_scene(mesh: Mesh, n_points: int = 100_000, noise_fraction: float = 0.0, normals: bool = True,
               seed: int = 0, name: str = "mesh") -> Scene:
    """Sample `n_points` from `mesh`; `noise_fraction` is a Gaussian standard deviation as a fraction
    of the bounding box's longest side; `normals=False` drops the normals."""
    size = float((mesh.bounds[1] - mesh.bounds[0]).max())
    cloud = cloud_from_mesh(mesh, n_points, noise=noise_fraction * size, seed=seed)
    text = f"{n_points} surface points, noise {noise_fraction:.2%} of the box, {'with' if normals else 'no'} normals"
    return Scene(name, cloud if normals else cloud.with_normals(None), mesh, description=text)


@lru_cache(maxsize=16)
def bunny_points(name: str = "bunny", n_points: int = 100_000, noise_fraction: float = 0.0, normals: bool = True,
                 seed: int = 0) -> Scene:
    """`n_points` area-uniform samples of the watertight bunny (the `data` extra), as `mesh_scene`."""
    return mesh_scene(_bunny_mesh(), n_points, noise_fraction, normals, seed, name=name)


@lru_cache(maxsize=16)
def analytic_scene(shape: str = "sphere", n_points: int = 20_000, noise_fraction: float = 0.0, normals: bool = True,
                   seed: int = 0, name: str | None = None) -> Scene:
    """Samples of an analytic shape (sphere, torus, box); the ground truth is its fine tessellation."""
    return mesh_scene(analytic_shape(shape).mesh(), n_points, noise_fraction, normals, seed, name=name or shape)


def file_scene(path: str | Path, ground_truth: str | Path | None = None, name: str | None = None,
               drop_isolated: bool = True) -> Scene:
    """A point cloud read from `path`, with an optional ground-truth mesh file; with `drop_isolated`, its stray
    points (`geometry.isolated_points`) dropped with a warning: they would stretch the fit's box around nothing."""
    mesh = read_mesh(ground_truth) if ground_truth is not None else None
    cloud = read_point_cloud(path)
    if drop_isolated and len(cloud) > 1 and (isolated := isolated_points(cloud.points)).any():
        warnings.warn(f"{path}: {int(isolated.sum())} of {len(cloud)} points lie far from all others (their 8th "
                      f"nearest point over 10 times the cloud's median such distance away): dropped as outliers "
                      f"(data.drop_isolated=false keeps them)", stacklevel=2)
        cloud = cloud.select(~isolated)
    return Scene(name or Path(path).stem, cloud, mesh, description=f"point cloud {path}")


def depth_scene(name: str, frames: DepthFrames, ground_truth: Mesh | None = None, hold_out_every: int = 0,
                cloud_stride: int = 1, description: str = "", near_distance: float | None = None) -> Scene:
    """A scene of depth frames: every `hold_out_every`-th frame (the 10th, 20th, ... for 10; 0 = none)
    is held out for scoring, the others are the input, also back-projected into a cloud (every
    `cloud_stride`-th pixel, image-space normals) for methods that take points."""
    held_out = None
    if hold_out_every == 1:
        raise ConfigError(f"{name}: hold_out_every=1 would hold out every frame; use 0 (none) or 2 and more")
    if hold_out_every and len(frames) < hold_out_every:
        warnings.warn(f"{name}: {len(frames)} frames, fewer than hold_out_every={hold_out_every}: none held out, "
                      f"so no held-out depth metrics", stacklevel=2)
    elif hold_out_every:
        index = torch.arange(len(frames))
        held_out, frames = frames[index[index % hold_out_every == hold_out_every - 1]], frames[
            index[index % hold_out_every != hold_out_every - 1]]
    cloud = depth_to_cloud(frames, stride=cloud_stride, with_normals=True)
    text = (f"{len(frames)} depth views {frames.width}x{frames.height}"
            + (f" (+{len(held_out)} held out)" if held_out is not None else "")
            + f", {len(cloud)} back-projected points" + (f"; {description}" if description else ""))
    return Scene(name, cloud, ground_truth, frames, text, held_out, depth_input=True, near_distance=near_distance)


@lru_cache(maxsize=8)
def bunny_depth(name: str = "bunny_depth", n_views: int = 24, width: int = 320, height: int = 240,
                noise: str = "kinect", seed: int = 0, stride: int = 1, hold_out_every: int = 0) -> Scene:
    """Synthetic depth views of the bunny (`scan_depth`, `noise` "none", "gaussian" or "kinect")."""
    mesh = _bunny_mesh()
    frames = scan_depth(mesh, n_views=n_views, width=width, height=height, noise=noise, seed=seed)
    return depth_scene(name, frames, mesh, hold_out_every, stride, f"{noise} noise")


POSES = ("files", "track", "auto")
"""Where an RGB-D scene's camera poses come from: the folder's pose files, tracking (`track_frames`; the
files, if any, are not read), or "auto": the files when the folder has them, else tracking."""


@lru_cache(maxsize=4)
def rgbd_scene(path: str, name: str | None = None, stride: int = 1, max_frames: int | None = None,
               hold_out_every: int = 10, cloud_stride: int = 4, ground_truth: str | None = None,
               near_distance: float | None = 0.05, poses: str = "files", sensor: str | None = None,
               colors: bool = False, photometric: float = 0.0) -> Scene:
    """A 7-Scenes, TUM or Redwood folder (`read_rgbd_folder`, every `stride`-th frame), or a folder of depth
    (and colour) images without poses (`read_depth_frames`, intrinsics from K file or `sensor`), as a depth
    scene with every `hold_out_every`-th frame held out; an optional ground-truth mesh file. `poses`: one of
    POSES; tracked poses (`track_frames`, its default settings) start at the identity and are kept in
    `Scene.trajectory`; `photometric` > 0: the tracker also aligns grey levels (`Tracker`, read from the colour
    images). `colors`: the frames carry the colour images (room meshes are coloured from them).
    A room: neural fields are meshed within `near_distance`
    metres of the input (None: everywhere)."""
    if poses not in POSES:
        raise ConfigError(f"poses must be one of {', '.join(POSES)} (where camera poses come from), got {poses!r}")
    with_files = poses == "files" or has_poses(path) or (poses == "auto" and not (Path(path) / "depth").is_dir())
    if poses == "files" or (poses == "auto" and with_files):  # read_rgbd_folder names what a folder lacks
        frames = read_rgbd_folder(path, stride=stride, max_frames=max_frames, with_color=colors)
        trajectory = None
    else:
        loaded = colors or photometric > 0
        frames = (read_rgbd_folder(path, stride=stride, max_frames=max_frames, with_color=loaded) if with_files
                  else read_depth_frames(path, sensor=sensor, stride=stride, max_frames=max_frames, with_color=loaded))
        trajectory = track_frames(frames, photometric=photometric).cam_to_world
        frames = DepthFrames(frames.depth, frames.K, trajectory.float(), frames.colors if colors else None)
    mesh = read_mesh(ground_truth) if ground_truth else None
    scene = depth_scene(name or Path(path).name, frames, mesh, hold_out_every, cloud_stride,
                        f"real RGB-D {path}" + (", tracked poses" if trajectory is not None else ""), near_distance)
    return replace(scene, trajectory=trajectory)


def rgbd_capture(name: str, folder: str, root: str | None = None, stride: int = 1, max_frames: int | None = None,
                 hold_out_every: int = 10, cloud_stride: int = 4, near_distance: float | None = 0.05,
                 colors: bool = False) -> Scene:
    """The RGB-D sequence in `folder` under `root`, $NEURALSURF_DATA or the fetch cache (`data_path`): every
    `stride`-th frame (at most `max_frames`), every `hold_out_every`-th of those held out for scoring
    (`rgbd_scene`). Raises SceneUnavailable naming the command that fetches it when the folder is absent."""
    path = data_path(root, folder)
    if not path.is_dir():
        raise scene_unavailable(path, folder)
    return rgbd_scene(str(path), name, stride, max_frames, hold_out_every, cloud_stride, near_distance=near_distance,
                      colors=colors)


def redkitchen(name: str = "redkitchen", root: str | None = None, folder: str = "7scenes_redkitchen_every10",
               stride: int = 1, max_frames: int | None = None, hold_out_every: int = 10, cloud_stride: int = 4,
               colors: bool = False) -> Scene:
    """The real 7-Scenes redkitchen frames: `folder` under `root`, $NEURALSURF_DATA or the fetch cache
    (`data_path`)."""
    return rgbd_capture(name, folder, root, stride, max_frames, hold_out_every, cloud_stride, colors=colors)


@lru_cache(maxsize=4)
def stanford_scans(name: str = "stanford_scans", root: str | None = None, conf: str = "stanford_bunny/data/bun.conf",
                   ground_truth: str = "stanford_bunny/reconstruction/bun_zipper.ply") -> Scene:
    """The real range scans of the Stanford bunny, aligned by their .conf and merged into one cloud
    (normals towards the scanners), and as one depth image per scan (read_range_scan_frames) for
    TSDF fusion; ground truth: Stanford's zippered reconstruction."""
    holder = Path(conf).parts[0]
    base = data_path(root, holder).parent  # both files from the same copy
    conf_path, gt_path = base / conf, base / ground_truth
    for path in (conf_path, gt_path):
        if not path.is_file():
            raise scene_unavailable(path, holder)
    clouds = read_range_scans(conf_path)
    points = torch.cat([c.points.double() for c in clouds])
    normals = torch.cat([c.normals.double() for c in clouds]) if all(c.has_normals for c in clouds) else None
    cloud = PointCloud(points, normals)
    text = f"{len(clouds)} real range scans aligned by {conf_path.name} ({len(cloud)} points)"
    return Scene(name, cloud, read_mesh(gt_path), read_range_scan_frames(conf_path), text)


# ----------------------------------------------------------------------------------------------
# photometric scenes: captures under known lights, and depth + normals from one rig


def _rig_view(mesh: Mesh, distance: float = 2.5) -> torch.Tensor:
    """Float64[Tensor, "4 4"]: a camera `distance` bounding-box sizes in front of the mesh (+z), looking at it."""
    lo, hi = mesh.bounds.double()
    center, extent = (lo + hi) / 2, float((hi - lo).max())
    return look_at(center + torch.tensor([0.0, 0.0, distance * extent], dtype=torch.float64), center, up=(0, 1, 0))


def _capture_scene(name: str, capture: PhotometricCapture, mesh: Mesh, text: str) -> Scene:
    """A one-view photometric scene; its cloud is the back-projection of the capture's exact depth."""
    frames = DepthFrames(capture.depth[None], capture.K[None], capture.cam_to_world[None])
    cloud = depth_to_cloud(frames, with_normals=True)
    return Scene(name, cloud, mesh, description=text, photometric=(capture,))


@lru_cache(maxsize=4)
def rig_lambertian(name: str = "rig_lambertian", size: int = 256, n_lights: int = 96, max_angle_deg: float = 45.0,
                   fov_deg: float = 30.0) -> Scene:
    """The bunny on the photometric rig, one view (size x size), `n_lights` DiLiGenT-like lights within
    `max_angle_deg` of the view axis: Lambertian (albedo 0.8), attached shadows only (no cast
    shadows), no noise. Ground truth: the rig's normal map."""
    mesh = _bunny_mesh()
    capture = render_photometric(mesh, cap_lights(n_lights, max_angle_deg), cam_to_world=_rig_view(mesh),
                                 width=size, height=size, fov_deg=fov_deg, shadows=False)[0]
    return _capture_scene(name, capture, mesh, f"bunny, 1 view {size}x{size}, {n_lights} lights, Lambertian, "
                                               f"no cast shadows, no noise")


@lru_cache(maxsize=4)
def rig_specular(name: str = "rig_specular", size: int = 256, n_lights: int = 96, max_angle_deg: float = 45.0,
                 fov_deg: float = 30.0, strength: float = 0.6, shininess: float = 40.0) -> Scene:
    """As `rig_lambertian` with a Blinn-Phong highlight (`strength`, `shininess`) and cast shadows."""
    mesh = _bunny_mesh()
    capture = render_photometric(mesh, cap_lights(n_lights, max_angle_deg), cam_to_world=_rig_view(mesh),
                                 width=size, height=size, fov_deg=fov_deg, shadows=True,
                                 specular=SpecularLobe("blinn_phong", strength=strength, shininess=shininess))[0]
    return _capture_scene(name, capture, mesh, f"bunny, 1 view {size}x{size}, {n_lights} lights, Blinn-Phong "
                                               f"highlights (strength {strength}, shininess {shininess}), cast shadows")


@lru_cache(maxsize=2)
def bunny_specular_ps(name: str = "bunny_specular_ps", root: str | None = None,
                      folder: str = "bunny_specular_ps") -> Scene:
    """The 50-light specular bunny capture (DiLiGenT layout) under the data root, with ground-truth
    normals. It has no depth and no camera: its cloud is the relief integrated from the ground-truth
    normals (orthographic, pixel units), only so that the scene is complete; score normals on it."""
    path = data_path(root, folder)
    if not path.is_dir():
        raise scene_unavailable(path, folder)
    capture = read_photometric(path)
    if capture.normals is None:
        raise SceneUnavailable(f"{path} has no ground-truth normals (Normal_gt.png / .mat) to score against")
    mask = capture.pixel_mask() & (capture.normals.norm(dim=-1) > 0.5)
    relief = integrate_least_squares(capture.normals, mask).depth
    v, u = torch.nonzero(mask, as_tuple=True)
    points = torch.stack([u.double(), v.double(), relief[mask].double()], -1)
    cloud = PointCloud(points, capture.normals[mask].double())
    return Scene(name, cloud, None, description=f"{len(capture)} lights, {capture.width}x{capture.height}, "
                                                 f"specular, real-data layout ({path})", photometric=(capture,),
                 cloud_from_truth=True)


@lru_cache(maxsize=4)
def rig_fusion(name: str = "rig_fusion", n_views: int = 8, width: int = 320, height: int = 240,
               fov_deg: float = 40.0, n_lights: int = 24, max_angle_deg: float = 45.0, depth_scale: int = 2,
               noise: str = "kinect", stereo: str = "robust", strength: float = 0.6, shininess: float = 40.0,
               image_noise: float = 0.005, seed: int = 0) -> Scene:
    """The bunny seen from `n_views` cameras on an orbit, each with a noisy depth map at 1/`depth_scale`
    of the resolution (`scan_depth`, `noise`, Kinect v1 by default) and photometric normals at full
    resolution: `n_lights` rig lights with Blinn-Phong highlights, cast shadows, sensor noise
    `image_noise` and 16-bit quantisation, solved by `stereo` photometric stereo (robust: IRLS).

    The input is the depth frames (`frames`, as for `bunny_depth`) and the stereo normal maps
    (`normal_maps`, one `PhotometricStereoResult` per view, camera frame, with confidence);
    `photometric` holds the rendered captures (images, lights, exact normals and depth)."""
    mesh = _bunny_mesh()
    vertices = mesh.vertices.double()
    lo, hi = vertices.min(0).values, vertices.max(0).values
    center = (lo + hi) / 2
    radius = float((vertices - center).norm(dim=-1).max())
    poses = orbit_cameras(center, radius, n_views, fov_deg, width / height)
    K = intrinsics_from_fov(width, height, fov_deg)
    captures = render_photometric(mesh, cap_lights(n_lights, max_angle_deg), cam_to_world=poses, K=K, width=width,
                                  height=height, specular=SpecularLobe("blinn_phong", strength=strength,
                                                                       shininess=shininess),
                                  shadows=True, noise_sigma=image_noise, bits=16, seed=seed)
    # the depth camera: same poses, 1/depth_scale of the pixels (pixel centres stay at integers)
    s = depth_scale
    K_depth = K.clone()
    K_depth[0, 0], K_depth[1, 1] = K[0, 0] / s, K[1, 1] / s
    K_depth[0, 2], K_depth[1, 2] = (K[0, 2] + 0.5) / s - 0.5, (K[1, 2] + 0.5) / s - 0.5
    frames = scan_depth(mesh, width=width // s, height=height // s, noise=noise, seed=seed, cam_to_world=poses,
                        K=K_depth)
    results = tuple(photometric_stereo(c, stereo) for c in captures)
    scene = depth_scene(name, frames, mesh, description=f"{noise} depth at {width // s}x{height // s}; "
                        f"{stereo} photometric stereo normals at {width}x{height} from {n_lights} lights "
                        f"(highlights, cast shadows)")
    return replace(scene, photometric=tuple(captures), normal_maps=results)


@dataclass(frozen=True)
class SceneSet:
    """Several scenes scored as one row of an evaluation (e.g. the test split of a shape collection):
    the method runs on each, the row holds the means of their metrics and the per-scene values."""

    name: str
    scenes: tuple[Scene, ...]
    description: str = ""
