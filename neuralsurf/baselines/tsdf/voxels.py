"""The voxel pass of TSDF fusion: projective signed distances of the voxels of some blocks as depth
images see them, and their running weighted averages (`fuse_blocks`).

For the voxels of the blocks and each frame: pixel coordinates by one small matmul per block and one
per block-local offset (K [R | t] folded with the grid), nearest-pixel projection, projective signed
distance sdf = depth(pixel) - z (positive in front of the surface, i.e. outside); then, frame after
frame, for the voxels where the depth is valid and sdf >= -truncation, the running weighted averages
of min(sdf, truncation): tsdf <- (W tsdf + w sdf) / (W + w), colour likewise, W <- min(W + w,
max_weight). Voxels never updated have weight 0 and count as unobserved.

In front of the surface every distance counts (the free space of the band's blocks is observed too): a
surface seen at a grazing angle has voxels just in front of it whose projective distances are many
truncations (1 / cos of the angle); an update limited to sdf <= some margin leaves them unobserved and
their cells unmeshed (with a margin of half a voxel it kept 0.64 of VoxelBlockGrid's mesh vertices on
10 frames of 7-Scenes at 1 cm; the band's blocks keep 0.98-1.0). Behind the surface the band ends at
-truncation along the ray, as in Open3D.

Every operation is a vectorised float op (on a CPU, bool tensors cost several float ops each).
"""

from __future__ import annotations

import torch
from torch import Tensor

from neuralsurf.cameras import kinect_sigma


def pixel_weights(depth: Tensor, weighting: str) -> Tensor:
    """Float[Tensor, "h w"] z-depth -> Float[Tensor, "h w"] weight of each pixel's observation."""
    if weighting == "constant":
        return torch.ones_like(depth)
    return (kinect_sigma(torch.tensor(0.4)) / kinect_sigma(depth)) ** 2


def world_to_camera(cam_to_world: Tensor) -> tuple[Tensor, Tensor]:
    """Float[Tensor, "... 4 4"] rigid poses -> rotations Float64[Tensor, "... 3 3"] and translations
    Float64[Tensor, "... 3"] with x_camera = rotation @ x_world + translation."""
    pose = cam_to_world.double()
    rotation = pose[..., :3, :3].transpose(-1, -2)
    return rotation, -(rotation @ pose[..., :3, 3:])[..., 0]


def camera_to_grid(cam_to_world: Tensor, origin: Tensor, voxel_size: float) -> tuple[Tensor, Tensor]:
    """Float[Tensor, "f 4 4"] poses -> rotations Float64[Tensor, "f 3 3"] and translations Float64[Tensor,
    "f 3"] with x_grid = rotation @ x_camera + translation, grid coordinates being voxel indices from
    `origin` Float64[Tensor, "3"]."""
    pose = cam_to_world.double()
    return pose[:, :3, :3] / voxel_size, (pose[:, :3, 3] - origin) / voxel_size


def grid_to_pixel(K: Tensor, cam_to_world: Tensor, origin: Tensor, voxel_size: float) -> Tensor:
    """Float[Tensor, "f 3 4"]: per frame, grid index (homogeneous) -> (z u, z v, z) with (u, v) pixel
    coordinates, K [R | t] composed with the grid (relative to `origin` for precision)."""
    rotation, translation = world_to_camera(cam_to_world)
    extrinsic = torch.cat([rotation * voxel_size, (rotation @ origin + translation)[..., None]], 2)
    return (K.double() @ extrinsic).float()


def pad_image(image: Tensor) -> Tensor:
    """Float[Tensor, "f h w ..."] -> Float[Tensor, "f h+2 w+2 ..."] with a border of zeros (invalid
    depth): pixel lookups clamped into the border need no bounds test."""
    border = [0, 0] * (image.ndim - 3) + [1, 1, 1, 1]
    return torch.nn.functional.pad(image, border)


def observe_blocks(
    blocks: Tensor, local: Tensor, projection: Tensor, padded: Tensor, truncation: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """Projective signed distances of the voxels of some blocks, as each of some depth images sees them.

    Args:
        blocks: Int64[Tensor, "m 3"] grid index of each block's first voxel.
        local: Float[Tensor, "v 3"] voxel offsets inside a block (v = block_size^3).
        projection: Float[Tensor, "f 3 4"] per frame, grid index (homogeneous) -> (z u, z v, z) with
            (u, v) pixel coordinates (K [R | t] composed with the grid's voxel size and origin).
        padded: Float[Tensor, "f h+2 w+2"] z-depth (0 = invalid) with a border of zeros (`pad_image`).
        truncation: Float[Tensor, ""] metres.
    Returns, over the voxels (f, m, v):
        seen Float[Tensor, "f m v"]: 1 where the voxel is in front of the camera and projects (nearest
        pixel) onto a valid depth d with d - z >= -truncation (any distance in front: free space
        too), else 0; sdf Float[Tensor, "f m v"] = min(d - z, truncation); pixel Int64[Tensor,
        "f m v"] index into the padded images flattened together (frame-major).
    """
    frames, rows, cols = padded.shape
    shifted = projection.clone()
    shifted[:, :2] += 1.5 * shifted[:, 2:]  # (z (u + 1.5), z (v + 1.5), z): floor(u + 1.5) = padded column
    linear = shifted[:, :, :3].transpose(1, 2)  # (f, 3, 3)
    base = (blocks.to(linear.dtype) @ linear + shifted[:, None, :, 3])[..., None]  # (f, m, 3, 1)
    offset = (local @ linear).transpose(1, 2)[:, None]  # (f, 1, 3, v)
    z = base[:, :, 2] + offset[:, :, 2]  # (f, m, v)
    # voxels at or behind the camera plane get huge coordinates, clamped into the zero border (invalid depth)
    inverse = z.clamp_min(1e-30).reciprocal_()
    column = (base[:, :, 0] + offset[:, :, 0]).mul_(inverse).clamp_(0, cols - 1).floor_()
    row = (base[:, :, 1] + offset[:, :, 1]).mul_(inverse).clamp_(0, rows - 1).floor_()
    if rows * cols * frames < 2**24:  # whole numbers stay exact in float32
        if frames > 1:
            row += (torch.arange(frames, device=z.device) * rows)[:, None, None]
        pixel = column.add_(row, alpha=cols).int()
    else:
        frame = torch.arange(frames, device=z.device)[:, None, None] * rows
        pixel = column.long() + (row.long() + frame) * cols
    observed = padded.view(-1).index_select(0, pixel.view(-1)).view(z.shape)
    valid = observed > 0
    sdf = observed.sub_(z)
    # 1 where sdf >= -truncation and the depth is valid, else 0, in float arithmetic: on a CPU, eager
    # bool tensors cost several float ops each; (sdf + truncation) * 1e30 + 1 is >= 1 or < 0
    seen = (sdf * 1e30).add_(truncation * 1e30 + 1.0).clamp_(0.0, 1.0).mul_(valid)
    return seen, torch.minimum(sdf, truncation), pixel


def fuse_blocks(
    tsdf: Tensor,
    weight: Tensor,
    color: Tensor | None,
    slots: Tensor,
    blocks: Tensor,
    local: Tensor,
    projection: Tensor,
    padded: Tensor,
    limits: Tensor,
    frame_mask: Tensor | None,
    weights: Tensor | None,
    colors: Tensor | None,
) -> None:
    """Fuse the observations of f frames, in order, into some blocks of a volume, in place: running
    weighted averages tsdf <- (W tsdf + w sdf) / (W + w), colour likewise, W <- min(W + w, cap); a
    voxel a frame does not see gets w = 0 from it, so nothing changes.

    Args:
        tsdf, weight: Float[Tensor, "s v"] the volume's values; color: Float[Tensor, "s v 3"] | None.
        slots: Int64[Tensor, "m"] the blocks' distinct slots in them; blocks, local, projection, padded:
            as `observe_blocks`.
        limits: Float[Tensor, "2"] truncation (metres) and the weight cap (inf: none).
        frame_mask: Float[Tensor, "f m"] 1 where a frame's band touches a block (None: all do).
        weights: Float[Tensor, "p"] per-pixel weights of the padded images, flattened (None = 1);
        colors: Float[Tensor, "p 3"] | None their colours.
    """
    seen, sdf, pixel = observe_blocks(blocks, local, projection, padded, limits[0])
    if frame_mask is not None:
        seen = seen * frame_mask[..., None]
    average, total = tsdf.index_select(0, slots), weight.index_select(0, slots)
    average_color = None if color is None else color.index_select(0, slots)
    for i in range(len(seen)):
        new = seen[i] if weights is None else seen[i] * weights[pixel[i]]
        total = total + new
        share = new / total.clamp_min(torch.finfo(total.dtype).tiny)  # of the new observation
        average = torch.lerp(average, sdf[i], share)
        total = total.clamp_max_(limits[1])
        if color is not None:
            average_color = torch.lerp(average_color, colors[pixel[i]], share[..., None])
    tsdf.index_copy_(0, slots, average)
    weight.index_copy_(0, slots, total)
    if color is not None:
        color.index_copy_(0, slots, average_color)


__all__ = ["camera_to_grid", "fuse_blocks", "grid_to_pixel", "observe_blocks", "pad_image", "pixel_weights", "world_to_camera"]
