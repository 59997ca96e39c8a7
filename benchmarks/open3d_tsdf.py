"""Open3D's TSDF fusions on neuralsurf's inputs: the references that tests/test_tsdf.py and the TSDF
benchmarks compare `neuralsurf.baselines.TSDFVolume` with (importable from both: the benchmarks run
from this folder, the tests put it on sys.path)."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import open3d.core as o3c

from neuralsurf.extract import as_bounds
from neuralsurf.structures import DepthFrames, Mesh, float_colors


def fuse_open3d(
    frames: DepthFrames, bounds, voxel_size: float, truncation: float, with_color: bool = False
) -> Mesh:
    """Reference: Open3D's UniformTSDFVolume on the same frames, its voxel centres on our grid points.

    The uniform volume is a cube of `resolution` voxels per side covering `bounds`; its voxel centres
    `origin + (i + 0.5) voxel_size` coincide with TSDFVolume's grid points `bounds[0] + i voxel_size`.
    Note that Open3D updates every voxel with sdf > -truncation (free space included) and measures
    sdf along the ray, not along z, so the two volumes differ away from the surface.
    """
    box = as_bounds(bounds)
    resolution = int(np.ceil((box[1] - box[0]).max() / voxel_size)) + 1
    integration = o3d.pipelines.integration
    color_type = (
        integration.TSDFVolumeColorType.RGB8 if with_color else integration.TSDFVolumeColorType.NoColor
    )
    volume = integration.UniformTSDFVolume(
        length=resolution * voxel_size,
        resolution=resolution,
        sdf_trunc=truncation,
        color_type=color_type,
        origin=box[0] - 0.5 * voxel_size,
    )
    for i in range(len(frames)):
        volume.integrate(*open3d_frame(frames[i], with_color))
    return Mesh.from_open3d(volume.extract_triangle_mesh())


def voxel_block_grid(voxel_size: float, block_size: int = 8, device: str = "CPU:0", capacity: int = 50_000):
    """An empty Open3D VoxelBlockGrid (tensor API) with float tsdf and weight, as Open3D's examples
    make it; its grid points are whole multiples of `voxel_size` in the world frame."""
    return o3d.t.geometry.VoxelBlockGrid(
        ("tsdf", "weight"), (o3c.float32, o3c.float32), ((1), (1)), voxel_size, block_size, capacity,
        o3c.Device(device),
    )


def voxel_block_grid_inputs(frames: DepthFrames, device: str = "CPU:0") -> list[tuple]:
    """Per frame, Open3D's (depth Image in metres, intrinsic, extrinsic = world_to_camera) tensors."""
    inputs = []
    for i in range(len(frames)):
        depth = o3d.t.geometry.Image(o3c.Tensor(frames.depth[i].cpu().numpy())).to(o3c.Device(device))
        intrinsic = o3c.Tensor(frames.K[i].double().cpu().numpy())
        extrinsic = o3c.Tensor(np.linalg.inv(frames.cam_to_world[i].double().cpu().numpy()))
        inputs.append((depth, intrinsic, extrinsic))
    return inputs


def integrate_voxel_block_grid(grid, inputs: list[tuple], voxel_size: float, truncation: float) -> None:
    """Open3D's fastest fusion path, frame by frame: compute_unique_block_coordinates, then integrate,
    with truncation = trunc_voxel_multiplier * voxel_size and no depth limit."""
    multiplier = truncation / voxel_size
    for depth, intrinsic, extrinsic in inputs:
        blocks = grid.compute_unique_block_coordinates(depth, intrinsic, extrinsic, 1.0, 1e6, multiplier)
        grid.integrate(blocks, depth, intrinsic, extrinsic, 1.0, 1e6, multiplier)


def fuse_voxel_block_grid(
    frames: DepthFrames, voxel_size: float, truncation: float, block_size: int = 8, device: str = "CPU:0"
) -> Mesh:
    """Reference: Open3D's VoxelBlockGrid on the same frames; the mesh of every voxel observed once
    or more, as TSDFVolume meshes (Open3D keeps voxels with weight > weight_threshold: 0 here; its
    default, 3, needs four observations). Its grid points are
    whole multiples of the voxel size: TSDFVolume's coincide when its bounds start on one.
    Open3D reads the depth at the pixel floor(u), floor(v) (TSDFVolume: the nearest pixel)."""
    grid = voxel_block_grid(voxel_size, block_size, device)
    integrate_voxel_block_grid(grid, voxel_block_grid_inputs(frames, device), voxel_size, truncation)
    return Mesh.from_open3d(grid.extract_triangle_mesh(weight_threshold=0.0).to_legacy())


def open3d_frame(frame: DepthFrames, with_color: bool = False):
    """One frame as Open3D's (RGBDImage, PinholeCameraIntrinsic, extrinsic = world_to_camera)."""
    h, w = frame.height, frame.width
    K = frame.K[0].double().cpu().numpy()
    intrinsic = o3d.camera.PinholeCameraIntrinsic(w, h, K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    color = np.zeros((h, w, 3), np.uint8)
    if with_color and frame.colors is not None:
        color = np.ascontiguousarray((float_colors(frame.colors[0]).cpu().numpy() * 255).round().astype(np.uint8))
    rgbd = o3d.geometry.RGBDImage.create_from_color_and_depth(
        o3d.geometry.Image(color),
        o3d.geometry.Image(np.ascontiguousarray(frame.depth[0].cpu().numpy())),
        depth_scale=1.0,
        depth_trunc=1e6,
        convert_rgb_to_intensity=False,
    )
    extrinsic = np.linalg.inv(frame.cam_to_world[0].double().cpu().numpy())
    return rgbd, intrinsic, extrinsic
