"""evaluate.py's methods for rooms: the library's voxel fit (`neuralsurf.rooms.fit_room`), the same fit at camera
poses tracked with the scene's poses hidden (`tracked_room`), and Open3D's VoxelBlockGrid TSDF fusion as the
reference, on the same frames."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from neuralsurf.baselines.tracking import Tracker, TrackingLostError, track_frames
from neuralsurf.cameras import render_depth
from neuralsurf.devices import resolve_device
from neuralsurf.evaluation.methods import NotApplicable, input_box, scene_input
from neuralsurf.metrics import absolute_trajectory_error, align_trajectory, depth_metrics, relative_pose_error
from neuralsurf.rooms import RoomSettings, fit_room
from neuralsurf.scenes import Scene
from neuralsurf.structures import DepthFrames, Mesh


@dataclass(frozen=True)
class ScoredMesh:
    """A method's mesh with metrics only the method can measure (a tracker's trajectory errors)."""

    mesh: Mesh
    """The reconstruction, world frame."""
    metrics: dict[str, float]
    """Named figures added to the method's row."""


def neural_voxels(scene: Scene, *, voxel: float = 0.01, truncation: float = 0.04, margin: float = 0.1,
                  object_voxel_fraction: float = 1 / 512, truncation_voxels: float = 4.0, margin_fraction: float = 0.02,
                  pixel_stride: int = 8, n_band: int = 2, prior_weight: float = 10.0, iterations: int = 5,
                  device: str = "auto", seed: int = 0, run_dir: str | Path | None = None,
                  config: dict | None = None) -> Mesh:
    """A method of evaluate.py for depth captures: `fit_room` of the scene's frames. A room (a scene with a
    `near_distance`) takes `voxel`, `truncation` and `margin` in metres, the same for every room; an object takes
    voxels of `object_voxel_fraction` of its input's box, `truncation_voxels` of them, and `margin_fraction` of the
    box. `seed`, `run_dir` and `config` are taken as every method takes them; the solve is deterministic and
    writes nothing."""
    if scene.frames is None:
        raise NotApplicable(f"the voxel fit needs depth frames; {scene_input(scene)}")
    if scene.near_distance is None:  # an object: sizes in proportion to its box
        _, size = input_box(scene, 0.0)
        voxel = object_voxel_fraction * size
        truncation, margin = truncation_voxels * voxel, margin_fraction * size
    settings = RoomSettings(voxel, truncation, margin, pixel_stride, n_band, prior_weight, iterations, colors=False)
    return fit_room(scene.frames, settings, str(resolve_device(device))).mesh


def open3d_tsdf(scene: Scene, *, voxel: float = 0.01, truncation_voxels: float = 4.0, weight_threshold: float = 0.0,
                depth_max: float | None = None, block_size: int = 16, device: str = "auto", seed: int = 0,
                run_dir: str | Path | None = None, config: dict | None = None) -> Mesh:
    """The reference: Open3D's VoxelBlockGrid (tensor API, its fastest fusion path) on the scene's frames, at
    `voxel` metres with truncation `truncation_voxels` voxels and no depth limit (`depth_max`: metres), meshed
    where the weight exceeds `weight_threshold` (Open3D's own default 3 drops surfaces seen fewer than four
    times). Runs on CUDA when `device` resolves to it."""
    import open3d as o3d
    import open3d.core as o3c

    if scene.frames is None:
        raise NotApplicable(f"Open3D's TSDF fusion needs depth frames; {scene_input(scene)}")
    frames = scene.frames
    where = o3c.Device("CUDA:0" if resolve_device(device).type == "cuda" and o3d.core.cuda.is_available() else "CPU:0")
    grid = o3d.t.geometry.VoxelBlockGrid(("tsdf", "weight"), (o3c.float32, o3c.float32), (1, 1), voxel, block_size,
                                         50_000, where)
    limit = float(depth_max) if depth_max is not None else float(frames.depth.max()) + 1.0
    for i in range(len(frames)):
        depth = o3d.t.geometry.Image(o3c.Tensor(frames.depth[i].cpu().numpy())).to(where)
        intrinsic = o3c.Tensor(frames.K[i].double().cpu().numpy())
        extrinsic = o3c.Tensor(np.linalg.inv(frames.cam_to_world[i].double().cpu().numpy()))
        blocks = grid.compute_unique_block_coordinates(depth, intrinsic, extrinsic, 1.0, limit, truncation_voxels)
        grid.integrate(blocks, depth, intrinsic, extrinsic, 1.0, limit, truncation_voxels)
    mesh = grid.extract_triangle_mesh(weight_threshold=weight_threshold).cpu()
    vertices = torch.from_numpy(mesh.vertex.positions.numpy().astype(np.float32))
    faces = torch.from_numpy(mesh.triangle.indices.numpy().astype(np.int64))
    return Mesh(vertices, faces)


def localised_poses(mesh: Mesh, frames: DepthFrames, rounds: int = 2) -> tuple[Tensor, int]:
    """Poses of depth `frames` registered to `mesh`: from each frame's own pose, `rounds` times, the mesh's depth
    ray-cast from every frame's current pose (one ray-casting scene a round) and each frame's depth registered
    onto it (the tracker's frame-to-frame ICP, at full size and every pixel).
    Returns Float64[Tensor, "n 4 4"] camera-to-world and the number of frames that could not be registered
    (they keep their pose)."""
    given = frames.cam_to_world.double().cpu()
    poses, K, lost = given.clone(), frames.K.cpu(), torch.zeros(len(frames), dtype=torch.bool)
    for _ in range(rounds):
        rendered, _ = render_depth(mesh, K, poses, frames.width, frames.height)
        for i in torch.nonzero(~lost).flatten().tolist():
            tracker = Tracker(K[i], mode="frame", initial_pose=poses[i], constant_velocity=False, downsample=0,
                              finest_stride=1)
            tracker.track(rendered[i])
            try:
                poses[i] = tracker.track(frames.depth[i].cpu())
            except TrackingLostError:
                poses[i], lost[i] = given[i], True
    return poses, int(lost.sum())


def localised_depth_metrics(mesh: Mesh, held_out: DepthFrames) -> dict[str, float]:
    """`depth_metrics` of `mesh` seen from the held-out frames at their `localised_poses` (the protocol of pose-free
    reconstruction: a mesh made at estimated poses is scored from views registered to it, so that its shape is
    scored and not the offset of its trajectory), as localised_<metric>, with localised_lost_frames."""
    poses, lost = localised_poses(mesh, held_out)
    located = DepthFrames(held_out.depth.cpu(), held_out.K.cpu(), poses.float())
    scores = depth_metrics(mesh, located)
    return {f"localised_{name}": scores[name] for name in ("depth_error_mean", "depth_error_median",
                                                           "depth_completeness")} | {"localised_lost_frames": lost}


def tracked_room(scene: Scene, *, mode: str = "model", voxel: float = 0.01, truncation: float = 0.04,
                 device: str = "auto", seed: int = 0, run_dir: str | Path | None = None,
                 config: dict | None = None) -> ScoredMesh:
    """The room fit (`fit_room`, `voxel` / `truncation` metres) at camera poses tracked from the fitted frames'
    depth alone (`track_frames` in `mode`, "model" or "frame"): the scene's poses are hidden from the tracker and
    used only to score its trajectory (`tracking_ate`, `tracking_rpe_m` / `_deg` per fitted frame, TUM's
    definitions) and to place it in the scene's frame (the rigid alignment ATE makes) so that the held-out views
    score the mesh. Raises TrackingLostError (the row fails, naming the frame) when tracking is lost."""
    if scene.frames is None or scene.near_distance is None:
        raise NotApplicable(f"tracking needs a room's depth frames; {scene.name} is not a room capture")
    frames = scene.frames
    where = resolve_device(device)
    trajectory = track_frames(frames.to(where), progress=False, mode=mode)
    tracked, truth = trajectory.cam_to_world.double().cpu(), frames.cam_to_world.double().cpu()
    placed = align_trajectory(tracked, truth) @ tracked
    fitted = DepthFrames(frames.depth, frames.K, placed.float(), frames.colors)
    settings = RoomSettings(voxel, truncation, colors=False)
    drift = relative_pose_error(tracked, truth)
    mesh = fit_room(fitted, settings, str(where)).mesh
    localised = localised_depth_metrics(mesh, scene.held_out) if scene.held_out is not None else {}
    return ScoredMesh(mesh, {
        "tracking_ate": absolute_trajectory_error(tracked, truth), "tracking_rpe_m": drift.translation,
        "tracking_rpe_deg": drift.rotation, "tracking_ms_per_frame": 1000 * trajectory.seconds / len(frames)}
        | localised)
