"""Camera tracking of a depth sequence without poses (KinectFusion, Newcombe et al. 2011).

`track_frames(frames)` returns a camera-to-world pose per frame, the first at `initial_pose`:

- **Frame-to-model** (`mode="model"`, KinectFusion): each frame is registered to the surface raycast
  from the TSDF volume fused so far (`TSDFVolume`), seen from the previous pose, then fused at the pose
  found. The raycast starts each ray at the previous frame's depth (the surface the last fused frame saw
  along it) and steps to the zero crossing of the trilinear TSDF (`raycast_volume`).
- **Frame-to-frame** (`mode="frame"`): each frame is registered to the previous frame's depth; no
  volume, faster, drifts more.

Registration: point-to-plane Gauss-Newton ICP with projective data association (a source point is
matched with the model pixel it projects to), coarse to fine over an image pyramid (2 x 2 block
averages of the depth), with a robust kernel (Huber or Tukey) on the residuals and correspondences
rejected beyond `max_distance` or with normals apart by more than `max_normal_angle`. Frame k starts
from frame k-1's pose moved by the motion from frame k-2 to k-1 (constant velocity).

With colour (`photometric` > 0 and colour images registered to the depth), each Gauss-Newton step also
minimises the grey-level differences between the frame's pixels and the previous frame's image where they
project (direct photometric alignment, as in RGB-D odometry: Steinbruecker et al. 2011, Kerl et al. 2013),
weighted `photometric` metres per unit of grey level against the point-to-plane distances.

VGA frames are registered and fused at half size (`downsample`: 2 x 2 block means, which also average the sensor's
noise; a 2 cm voxel still spans pixels there). On a CPU the two loops that dominate a frame, the raycast's volume sampling and the
ICP iterations' sums, can run compiled (`compiled=True`; `track_frames` compiles long sequences).

Tracking is lost when too few of the frame's points find an inlier (`min_inlier_share`), when their
point-to-plane RMSE is above `max_rmse`, or when the normal equations are degenerate: the tracker raises
`TrackingLostError` naming the frame, instead of fusing it at a wrong pose.

Everything runs on the frames' device (CUDA tensors: CUDA) with vectorised torch ops.
"""

from __future__ import annotations

import functools
import math
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from functools import cached_property

import torch
from torch import Tensor

from neuralsurf.baselines.registration.estimation import small_motion
from neuralsurf.baselines.tsdf import FusionSettings, TSDFVolume
from neuralsurf.cameras import backproject_depth_to_camera, depth_normals, pixel_rays
from neuralsurf.devices import CompiledOnCPU
from neuralsurf.errors import ConfigError, InputError, NeuralsurfError
from neuralsurf.progress import progress_bar
from neuralsurf.structures import DepthFrames, float_colors

MODES = ("model", "frame")
"""Frame-to-model (KinectFusion) or frame-to-frame tracking."""


class TrackingLostError(NeuralsurfError, RuntimeError):
    """A frame could not be registered: its index, inlier share and residual are attributes."""

    def __init__(self, frame: int, inlier_share: float, rmse: float, reason: str):
        self.frame, self.inlier_share, self.rmse = frame, inlier_share, rmse
        super().__init__(
            f"tracking lost at frame {frame}: {reason} (inlier share {inlier_share:.3f}, point-to-plane RMSE "
            f"{rmse * 1000:.1f} mm); the camera moved too far or saw another scene. Track fewer frames apart "
            f"(a smaller stride), raise max_distance, or start a new sequence at this frame"
        )


@dataclass(frozen=True)
class Trajectory:
    """Camera poses estimated by `track_frames`, with per-frame registration statistics."""

    cam_to_world: Tensor
    """Float64[Tensor, "n 4 4"]: camera-to-world pose of every frame (CPU)."""
    inlier_share: Tensor
    """Float64[Tensor, "n"]: share of the frame's valid points matched within the thresholds (1 for frame 0)."""
    rmse: Tensor
    """Float64[Tensor, "n"]: point-to-plane RMSE (metres) of those inliers (0 for frame 0)."""
    seconds: float
    """Wall-clock time of the whole tracking (fusion included)."""


# ----------------------------------------------------------------------------- image pyramid


def downsample_depth(depth: Tensor, max_jump: float) -> Tensor:
    """Depth images Float[Tensor, "... h w"] -> Float[Tensor, "... h//2 w//2"]: each 2 x 2 block's mean over
    its valid pixels within `max_jump` metres of the block's nearest valid depth (a block across a
    discontinuity keeps its nearer surface); 0 where the block has no valid pixel."""
    h, w = depth.shape[-2] // 2 * 2, depth.shape[-1] // 2 * 2
    corners = [depth[..., row:h:2, column:w:2] for row in (0, 1) for column in (0, 1)]  # views, no copy
    nearest = functools.reduce(torch.minimum, [torch.where(corner > 0, corner, torch.inf) for corner in corners])
    total, count = torch.zeros_like(nearest), torch.zeros_like(nearest)
    for corner in corners:
        use = (corner > 0) & (corner - nearest <= max_jump)
        total, count = total + corner * use, count + use
    return torch.where(count > 0, total / count.clamp_min(1), 0.0)


def downsample_intrinsics(K: Tensor) -> Tensor:
    """Float[Tensor, "... 3 3"] -> the intrinsics of the half-size image of `downsample_depth`: pixel (u', v')
    covers pixels 2u', 2u' + 1 (and rows alike), so u' = (u - 0.5) / 2."""
    half = K.clone()
    half[..., :2, :] = K[..., :2, :] / 2
    half[..., :2, 2] = (K[..., :2, 2] - 0.5) / 2
    return half


def bilateral_filter(depth: Tensor, radius: int = 2, sigma_space: float = 2.0, sigma_range: float = 0.03) -> Tensor:
    """Edge-preserving smoothing of a depth image Float[Tensor, "h w"] (KinectFusion's first step): each valid
    pixel becomes the mean of the valid pixels within `radius`, weighted by exp(-d^2 / 2 sigma_space^2) of
    their distance d (pixels) and exp(-dz^2 / 2 sigma_range^2) of their depth difference dz (metres)."""
    h, w = depth.shape
    side = 2 * radius + 1
    patches = torch.nn.functional.unfold(depth[None, None], side, padding=radius)[0]  # (side^2, h w)
    offsets = torch.arange(side, dtype=depth.dtype, device=depth.device) - radius
    space = torch.exp(-(offsets[:, None] ** 2 + offsets[None, :] ** 2) / (2 * sigma_space**2)).reshape(-1, 1)
    centre = depth.reshape(1, -1)
    weights = space * torch.exp(-((patches - centre) ** 2) / (2 * sigma_range**2)) * (patches > 0)
    smooth = (weights * patches).sum(0) / weights.sum(0).clamp_min(1e-12)
    return torch.where(depth > 0, smooth.reshape(h, w), 0.0)


def depth_pyramid(depth: Tensor, K: Tensor, levels: int, max_jump: float, compiled: bool = False
                  ) -> list[tuple[Tensor, Tensor]]:
    """[(depth Float[Tensor, "h_l w_l"], K Float[Tensor, "3 3"])] for levels 0 (the input) to levels - 1,
    each half the size of the one before (`downsample_depth`, `downsample_intrinsics`; `compiled`: the
    downsampling through torch.compile on a CPU)."""
    downsample = implementation(downsample_depth, compiled, depth.device)
    pyramid = [(depth, K)]
    for _ in range(levels - 1):
        depth, K = downsample(depth, max_jump), downsample_intrinsics(K)
        pyramid.append((depth, K))
    return pyramid


@dataclass(frozen=True)
class SurfaceMap:
    """Camera-frame points and normals of one depth image (one pyramid level)."""

    points: Tensor
    """Float[Tensor, "h w 3"]: back-projected pixels (camera frame)."""
    normals: Tensor
    """Float[Tensor, "h w 3"]: unit normals facing the camera."""
    valid: Tensor
    """Bool[Tensor, "h w"]: pixels with a depth and a normal."""
    K: Tensor
    """Float[Tensor, "3 3"]: the level's intrinsics."""

    @cached_property
    def packed(self) -> Tensor:
        """Float[Tensor, "h*w 6"]: points and normals side by side (one gather finds both)."""
        return torch.cat([self.points, self.normals], -1).reshape(-1, 6)


def surface_map(depth: Tensor, K: Tensor, stride: int = 1) -> tuple[Tensor, Tensor, Tensor]:
    """Camera-frame points and normals Float[Tensor, "h' w' 3"] and their validity Bool[Tensor, "h' w'"] of a depth
    image Float[Tensor, "h w"] at every `stride`-th row and column; normals from image neighbours
    (`cameras.depth_normals`, discontinuities above 5 % of the depth)."""
    points = backproject_depth_to_camera(depth[None], K[None])
    normals, has = depth_normals(points, 0.05, stride)
    valid = has[0] & (depth[::stride, ::stride] > 0)
    return points[0, ::stride, ::stride], normals[0], valid


def surface_maps(depth: Tensor, K: Tensor, levels: int, max_jump: float, stride: int = 1,
                 compiled: bool = False) -> list[SurfaceMap]:
    """`SurfaceMap` of every level of `depth_pyramid(depth Float[Tensor, "h w"], K, levels, max_jump)`
    (`surface_map`; `compiled`: through torch.compile on a CPU). `stride`: level 0 keeps every stride-th row
    and column only (a source's points, not a model's pixels)."""
    one_map = implementation(surface_map, compiled, depth.device)
    return [SurfaceMap(*one_map(level_depth, level_K, stride if level == 0 else 1), level_K)
            for level, (level_depth, level_K) in enumerate(depth_pyramid(depth, K, levels, max_jump, compiled))]


def grey_levels(colors: Tensor) -> Tensor:
    """Grey levels Float[Tensor, "h w"] in [0, 1] of a colour image Float[Tensor, "h w 3"] in [0, 1] (Rec. 601 luma)."""
    return colors @ torch.tensor([0.299, 0.587, 0.114], dtype=colors.dtype, device=colors.device)


def grey_pyramid(grey: Tensor, levels: int) -> list[Tensor]:
    """Grey images Float[Tensor, "h_l w_l"] for levels 0 (the input Float[Tensor, "h w"]) to levels - 1, each
    the 2 x 2 block means of the one before (the pixels of `depth_pyramid`'s levels)."""
    pyramid = [grey]
    for _ in range(levels - 1):
        pyramid.append(torch.nn.functional.avg_pool2d(pyramid[-1][None, None], 2)[0, 0])
    return pyramid


def with_gradients(grey: Tensor) -> Tensor:
    """Float[Tensor, "3 h w"]: a grey image Float[Tensor, "h w"] and its central-difference derivatives along u
    and v (grey levels per pixel; 0 on the border)."""
    du, dv = torch.zeros_like(grey), torch.zeros_like(grey)
    du[:, 1:-1] = (grey[:, 2:] - grey[:, :-2]) / 2
    dv[1:-1] = (grey[2:] - grey[:-2]) / 2
    return torch.stack([grey, du, dv])


def moved_and_projected(points: Tensor, transform: Tensor, K: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Points Float[Tensor, "n 3"] moved by `transform` Float[Tensor, "4 4"] into a camera with intrinsics K, and
    their pixel coordinates u, v and 1 / z (Float[Tensor, "n"] each; 1 where z <= 0, which callers reject)."""
    moved = points @ transform[:3, :3].T + transform[:3, 3]
    x, y, z = moved.unbind(1)
    inverse_z = 1 / torch.where(z > 0, z, 1.0)
    return moved, (K[0, 0] * x + K[0, 1] * y) * inverse_z + K[0, 2], K[1, 1] * y * inverse_z + K[1, 2], inverse_z


def photometric_rows(points: Tensor, grey: Tensor, transform: Tensor, target: Tensor, K: Tensor
                     ) -> tuple[Tensor, Tensor]:
    """Rows [J | r] Float[Tensor, "n 7"] of the grey-level residuals r_i = I(pi(q_i)) - g_i of source points p_i
    Float[Tensor, "n 3"] with grey levels g_i Float[Tensor, "n"], moved by `transform` Float[Tensor, "4 4"] to
    q_i in the camera (intrinsics K) of a target image I with its derivatives (`with_gradients`, Float[Tensor,
    "3 h w"], sampled bilinearly), linearised in a small motion (omega, t) of q_i as `point_to_plane_rows`:
    J_i = (q_i x d_i, d_i) with d_i = grad I . d pi / d q. Also Bool[Tensor, "n"]: q_i projects inside the image."""
    q, u, v, inverse_z = moved_and_projected(points, transform, K)
    x, y, z = q.unbind(1)
    h, w = target.shape[1:]
    inside = (z > 0) & (u >= 1) & (u <= w - 2) & (v >= 1) & (v <= h - 2)
    where = torch.stack([u / (w - 1), v / (h - 1)], -1) * 2 - 1
    sampled = torch.nn.functional.grid_sample(target[None], where[None, None], align_corners=True)[0, :, 0]  # (3, n)
    value, du, dv = sampled
    fx, fy = K[0, 0] * inverse_z, K[1, 1] * inverse_z
    d = torch.stack([du * fx, dv * fy, -(du * fx * x + dv * fy * y) * inverse_z], 1)  # (n, 3)
    residual = torch.where(inside, value - grey, 0.0)
    return torch.cat([torch.linalg.cross(q, d), d, residual[:, None]], 1), inside


def photometric_equations(points: Tensor, grey: Tensor, transform: Tensor, target: Tensor, K: Tensor,
                          kernel_scale: float) -> Tensor:
    """Huber-weighted normal equations Float[Tensor, "7 7"] of `photometric_rows` (pixels outside the target weigh 0)."""
    rows, inside = photometric_rows(points, grey, transform, target, K)
    weights = robust_weights(rows[:, 6], "huber", kernel_scale) * inside
    return (rows * weights[:, None]).T @ rows


# ----------------------------------------------------------------------------- raycast


def block_slots(volume: TSDFVolume) -> Tensor:
    """Int64[Tensor, "bx by bz"]: the storage slot of every block of `volume`'s grid, -1 where none is
    allocated (a lookup table for `trilinear_tsdf`, valid until the volume allocates more blocks)."""
    counts = [int(c) for c in volume.block_counts]
    slots = torch.full(counts, -1, dtype=torch.int64, device=volume.device)
    if volume.sparse:
        slots.view(-1)[volume._keys] = volume._slots
    else:
        slots.view(-1)[: volume._used] = torch.arange(volume._used, device=volume.device)
    return slots


def trilinear_tsdf(tsdf: Tensor, weight: Tensor, slots: Tensor, points: Tensor, block_size: int,
                   grid_shape: tuple[int, int, int]) -> Tensor:
    """Trilinear interpolation of block-stored fused distances at grid coordinates Float[Tensor, "m 3"]
    (voxel units from the grid's origin) -> Float[Tensor, "m"]; NaN where a corner is unobserved (weight 0)
    or outside the grid. `tsdf`, `weight`: Float[Tensor, "slots block_size^3"] (a `TSDFVolume`'s storage);
    `slots`: `block_slots` of the volume."""
    (_, by, bz), size = slots.shape, block_size
    base = points.floor()
    fraction = points - base
    base = base.long()
    total = torch.zeros_like(points[:, 0])
    for corner in range(8):  # one pass per corner: each a gather and a multiply-add, fused when compiled
        offset = ((corner >> 2) & 1, (corner >> 1) & 1, corner & 1)
        index = [base[:, axis] + offset[axis] for axis in range(3)]
        inside = (index[0] >= 0) & (index[1] >= 0) & (index[2] >= 0)
        inside &= (index[0] < grid_shape[0]) & (index[1] < grid_shape[1]) & (index[2] < grid_shape[2])
        i, j, k = (index[axis].clamp(0, grid_shape[axis] - 1) for axis in range(3))
        slot = slots.view(-1)[((i // size) * by + j // size) * bz + k // size]
        flat = slot.clamp_min(0) * size**3 + ((i % size) * size + j % size) * size + k % size
        observed = inside & (slot >= 0) & (weight.view(-1)[flat] > 0)
        share = torch.ones_like(total)
        for axis in range(3):
            share = share * (fraction[:, axis] if offset[axis] else 1 - fraction[:, axis])
        total = total + torch.where(observed, tsdf.view(-1)[flat].to(points), torch.nan) * share
    return total


def raycast_volume(volume: TSDFVolume, guide: Tensor, K: Tensor, cam_to_world: Tensor, steps: int = 1,
                   slots: Tensor | None = None, compiled: bool = False) -> Tensor:
    """Depth of the zero crossing of `volume`'s TSDF seen by a camera, found from a guess of it.

    The fused distances are projective z-differences (`baselines.tsdf.voxels`), so along a ray from a camera near
    the fusing ones the surface lies at z + tsdf(z): starting at `guide`, `steps` such updates of z
    (each a `trilinear_tsdf` sample), kept where the last sample was observed and within half the
    truncation of zero (not clipped: the surface is inside the band).

    Args:
        volume: the fused TSDF. guide: Float[Tensor, "h w"] z-depths to start from (0: no ray).
        K: Float[Tensor, "3 3"]; cam_to_world: Float[Tensor, "4 4"] the camera.
        steps: z updates per ray. slots: `block_slots(volume)` (computed when None).
        compiled: on a CPU, sample the volume through torch.compile (`implementation`).
    Returns:
        Float[Tensor, "h w"] z-depth of the surface, 0 where none was found.
    """
    if not (isinstance(steps, int) and steps >= 1):
        raise ConfigError(f"raycast steps must be a positive integer, got {steps!r}")
    slots = block_slots(volume) if slots is None else slots
    rays = pixel_rays(K, *guide.shape)  # (h, w, 3), z = 1
    searched = guide > 0
    pose = cam_to_world.to(guide)
    origin = torch.as_tensor(volume.origin, dtype=guide.dtype, device=guide.device)
    grid_rays = rays[searched] @ pose[:3, :3].T / volume.voxel_size  # (m, 3) grid units per unit of z
    start = (pose[:3, 3] - origin) / volume.voxel_size
    z = guide[searched]
    sample = implementation(trilinear_tsdf, compiled, guide.device)
    for _ in range(steps):
        value = sample(volume._tsdf, volume._weight, slots, start + z[:, None] * grid_rays, volume.block_size,
                       volume.grid_shape)
        z = z + torch.nan_to_num(value)
    depth = torch.zeros_like(guide)
    depth[searched] = torch.where(value.abs() < volume.truncation / 2, z, 0.0)  # NaN compares False
    return depth


# ----------------------------------------------------------------------------- ICP


def robust_weights(residuals: Tensor, kernel: str, scale: float) -> Tensor:
    """IRLS weights Float[Tensor, "n"] of residuals Float[Tensor, "n"]: "huber" min(1, scale / |r|);
    "tukey" (1 - (r / scale)^2)^2 within `scale`, else 0; "none" 1."""
    r = residuals.abs()
    if kernel == "huber":
        return torch.where(r <= scale, 1.0, scale / r.clamp_min(1e-30))
    if kernel == "tukey":
        return torch.where(r <= scale, (1 - (r / scale) ** 2) ** 2, 0.0)
    if kernel == "none":
        return torch.ones_like(r)
    raise ConfigError(f"unknown robust kernel {kernel!r}; use 'huber', 'tukey' or 'none'")


def point_to_plane_rows(source: Tensor, target: Tensor, normals: Tensor) -> Tensor:
    """Rows [J | r] Float[Tensor, "n 7"] of point-to-plane ICP linearised at the identity: r_i = n_i . (p_i - q_i)
    and J_i = (p_i x n_i, n_i), the derivative of r_i by a small motion (omega, t): exp(omega) p_i + t. `source`,
    `target`, `normals`: Float[Tensor, "n 3"] matched points p, q and target normals n."""
    (px, py, pz), (nx, ny, nz) = source.unbind(1), normals.unbind(1)
    residual = ((source - target) * normals).sum(1)
    return torch.stack([py * nz - pz * ny, pz * nx - px * nz, px * ny - py * nx, nx, ny, nz, residual], 1)


def gauss_newton_step(system: Tensor) -> Tensor | None:
    """The motion Float64[Tensor, "4 4"] [exp(omega) t; 0 1] minimising sum w_i (J_i x + r_i)^2 from its normal
    equations `system` = sum w_i [J_i r_i]^T [J_i r_i] (Float[Tensor, "7 7"]; `small_motion`, in float64 numpy,
    which solves a 6 x 6 system in less time than one torch op takes to dispatch); None when the 6 x 6 block is
    degenerate (a plane or a line constrains fewer than six directions)."""
    equations = system.double().cpu().numpy()
    motion = small_motion(equations[:6, :6], equations[:6, 6], 1e-9)
    return None if motion is None else torch.from_numpy(motion).to(system.device)


def point_to_plane_update(source: Tensor, target: Tensor, normals: Tensor, weights: Tensor) -> Tensor | None:
    """One Gauss-Newton step Float64[Tensor, "4 4"] of point-to-plane ICP on matched points (`point_to_plane_rows`)
    with weights Float[Tensor, "n"] (0 for rejected pairs), or None if degenerate (`gauss_newton_step`)."""
    rows = point_to_plane_rows(source, target, normals)
    return gauss_newton_step((rows * weights[:, None]).T @ rows)


def projective_matches(points: Tensor, normals: Tensor, transform: Tensor, model_packed: Tensor, model_valid: Tensor,
                       model_K: Tensor, max_distance: float, min_cosine: float) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Projective data association: source points Float[Tensor, "n 3"] with normals Float[Tensor, "n 3"] (source
    camera frame), moved by `transform` Float[Tensor, "4 4"] into the model camera, each matched with the model
    pixel it projects to (nearest) in a model map given by its `SurfaceMap.packed`, `valid` and `K` (all in the
    points' dtype). Returns the moved points, the matched model points and normals (Float[Tensor, "n 3"] each),
    and the inliers Bool[Tensor, "n"]: found, within `max_distance` and with normals agreeing to `min_cosine`."""
    moved, u, v, _ = moved_and_projected(points, transform, model_K)
    u, v, z = torch.round(u), torch.round(v), moved[:, 2]
    turned = normals @ transform[:3, :3].T
    h, w = model_valid.shape
    inside = (z > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    index = torch.where(inside, v * w + u, 0).long()
    found = inside & model_valid.reshape(-1)[index]
    matched = model_packed[index]  # (n, 6): point, normal
    target, target_normals = matched[:, :3], matched[:, 3:]
    close = (moved - target).square().sum(1) <= max_distance**2
    agree = (turned * target_normals).sum(1) >= min_cosine
    return moved, target, target_normals, found & close & agree


def icp_equations(points: Tensor, normals: Tensor, transform: Tensor, model_packed: Tensor, model_valid: Tensor,
                  model_K: Tensor, max_distance: float, min_cosine: float, kernel: str, kernel_scale: float
                  ) -> tuple[Tensor, Tensor, Tensor]:
    """One ICP iteration's sums over source points Float[Tensor, "n 3"] and normals Float[Tensor, "n 3"] moved by
    `transform` Float[Tensor, "4 4"] and matched in a model map (`projective_matches`; its `packed` Float[Tensor, "h*w 6"],
    `valid` Bool[Tensor, "h w"] and `K`): the robustly weighted normal equations Float[Tensor, "7 7"]
    (`point_to_plane_rows`, `robust_weights`; rejected pairs weigh 0), the inlier count Int[Tensor, ""] and the
    inliers' sum of squared residuals Float[Tensor, ""] (one function, so that it compiles to one loop)."""
    moved, target, target_normals, inlier = projective_matches(points, normals, transform, model_packed, model_valid,
                                                               model_K, max_distance, min_cosine)
    rows = point_to_plane_rows(moved, target, target_normals)
    residual = rows[:, 6]
    weights = robust_weights(residual, kernel, kernel_scale) * inlier
    squares = (residual.square() * inlier).sum()
    return (rows * weights[:, None]).T @ rows, inlier.sum(), squares


@dataclass(frozen=True)
class FrameFit:
    """The result of registering one frame to its model."""

    transform: Tensor
    """Float64[Tensor, "4 4"]: source camera -> model camera."""
    inlier_share: float
    """Share of the source's valid finest-level points that are inliers at `transform`."""
    rmse: float
    """Point-to-plane RMSE (metres) of those inliers."""
    degenerate: bool
    """The finest level's normal equations were singular."""


@dataclass(frozen=True)
class GreyPair:
    """The grey levels of a registration's source and target frames, one per pyramid level (finest first)."""

    source: list[Tensor]
    """Float[Tensor, "h_l w_l"]: the source's grey levels at its `SurfaceMap`s' pixels."""
    target: list[Tensor]
    """Float[Tensor, "3 h_l w_l"]: the target's grey image and its derivatives (`with_gradients`), seen by the model maps' camera."""
    weight: float
    """Metres per unit of grey level: the photometric rows' weight against the point-to-plane rows."""
    kernel_scale: float = 0.1
    """Huber scale of the grey-level residuals."""


def register_maps(source: list[SurfaceMap], model: list[SurfaceMap], init: Tensor, iterations: tuple[int, ...],
                  kernel: str, kernel_scale: float, max_distance: float, min_cosine: float,
                  compiled: bool = False, grey: GreyPair | None = None) -> FrameFit:
    """Point-to-plane ICP of a source pyramid onto a model pyramid (lists finest first, same length),
    coarse to fine from `init` Float64[Tensor, "4 4"] (source camera -> model camera); `iterations[l]`
    Gauss-Newton steps at level l (finest first). `compiled`: on a CPU, `icp_equations` through torch.compile.
    `grey`: each step also aligns the source's grey levels with the target's (`photometric_equations`)."""
    transform = init.double().clone()
    degenerate = False
    equations = implementation(icp_equations, compiled, source[0].points.device)

    def sums(level: int, points: Tensor, normals: Tensor) -> tuple[Tensor, int, float]:
        target = model[level]
        system, count, squares = equations(points, normals, transform.to(points), target.packed, target.valid,
                                           target.K.to(points), max_distance, min_cosine, kernel, kernel_scale)
        return system, int(count), float(squares)

    for level in reversed(range(len(source))):
        src, valid = source[level], source[level].valid
        points, normals = src.points[valid], src.normals[valid]
        source_grey = None if grey is None else grey.source[level][valid]
        for _ in range(iterations[level]):
            system, count, _ = sums(level, points, normals)
            if grey is not None:
                system = system + grey.weight**2 * photometric_equations(
                    points, source_grey, transform.to(points), grey.target[level], src.K.to(points), grey.kernel_scale)
            update = None if count < 6 else gauss_newton_step(system)
            degenerate = update is None
            if degenerate:
                break
            transform = update @ transform
            if float(update[:3, 3].norm()) < 1e-4 and float((update[:3, :3].diagonal().sum() - 1) / 2) > 1 - 5e-9:
                break  # converged: the step moved less than 0.1 mm and turned less than 1e-4 rad
    finest = source[0]
    points = finest.points[finest.valid]
    _, count, squares = sums(0, points, finest.normals[finest.valid])
    rmse = math.sqrt(squares / count) if count else math.inf
    return FrameFit(transform, count / max(len(points), 1), rmse, degenerate)


# ----------------------------------------------------------------------------- tracker


_COMPILED_FRAMES = 500
"""track_frames(compiled=None) compiles the tracker's loops on a CPU for sequences of this many frames or more.
Measured on the 2-core CPU (benchmarks/bench_tracking.py): compiling took 11 s from torch's on-disk cache and
about a minute without it; compiled frames took 28 ms (livingroom1) and 42 ms (redkitchen) less CPU than eager
ones, so compiling pays from a few hundred frames on."""


def implementation(function, compiled: bool, device: torch.device):
    """`function` itself, or (`compiled` on a CPU) its torch.compile'd form, compiled once per process."""
    return _COMPILED[function] if compiled and device.type == "cpu" else function


class Tracker:
    """Tracks depth frames one at a time (see the module docstring); `track(depth)` returns the pose.

    Args:
        K: Float[Tensor, "3 3"] intrinsics of every frame.
        mode: "model" (frame-to-model against the fused TSDF) or "frame" (frame-to-frame).
        levels: pyramid levels (level 0 the registered frame, see `downsample`).
        iterations: Gauss-Newton steps per level, finest first (one per level).
        kernel, kernel_scale: robust kernel ("huber", "tukey", "none") and its scale in metres.
        max_distance: correspondences further apart (metres) are rejected.
        max_normal_angle: correspondences whose normals differ by more (degrees) are rejected.
        min_inlier_share, max_rmse: below / above these a frame is lost (`TrackingLostError`).
        max_depth: readings beyond this (metres) are ignored (tracking and fusion).
        voxel_size, truncation: the TSDF volume of mode "model" (metres; truncation default 3 voxels).
        margin: the volume's box is the first frame's points grown by this (metres) in every direction.
        initial_pose: Float[Tensor, "4 4"] pose of the first frame (default identity).
        raycast_level: the pyramid level at which the model is raycast (0: the registered size; coarser is faster, and
            its coarser levels are downsampled from it; finer source levels associate with it).
        smoothing: radius (pixels) of the `bilateral_filter` of the depth that is registered (0: none).
        constant_velocity: start each frame's ICP from the previous frame's motion repeated (else from
            the previous pose, as KinectFusion).
        finest_stride: the finest level registers every finest_stride-th row and column of the frame
            (1: every pixel, as KinectFusion; 2, the default, is about 4 times cheaper there).
        downsample: frames are registered and fused at 1 / 2^downsample of their size (`depth_pyramid`'s block
            means; 0: full size); the pyramid's levels, the raycast and `finest_stride` count from there. None:
            the most halvings that keep the width at 320 pixels or more (1 for VGA frames, which tracked
            livingroom1 and redkitchen to the ATE of full size in a third of the time).
        compiled: on a CPU, run the raycast's volume sampling and the ICP iterations through torch.compile
            (`implementation`): about a third less CPU a frame after a compilation of 10 s (from torch's on-disk
            cache) to a minute.
        photometric: with colour, the weight (metres per unit of grey level) of the grey-level alignment with the
            previous frame in every Gauss-Newton step (`GreyPair`); 0: depth alone. Needs colour registered to the
            depth (`track(depth, colors)`).
    """

    def __init__(self, K: Tensor, mode: str = "model", levels: int = 3, iterations: tuple[int, ...] = (4, 5, 10),
                 kernel: str = "huber", kernel_scale: float = 0.01, max_distance: float = 0.1,
                 max_normal_angle: float = 30.0, min_inlier_share: float = 0.3, max_rmse: float = 0.03,
                 max_depth: float = 4.0, voxel_size: float = 0.02, truncation: float | None = None,
                 margin: float = 3.0, initial_pose: Tensor | None = None, raycast_level: int = 1,
                 smoothing: int = 0, constant_velocity: bool = True, finest_stride: int = 2,
                 downsample: int | None = None, compiled: bool = False, photometric: float = 0.0):
        if mode not in MODES:
            raise ConfigError(f"tracking mode must be one of {MODES}, got {mode!r}")
        if not (isinstance(levels, int) and levels >= 1) or len(iterations) != levels:
            raise ConfigError(f"levels must be a positive integer and iterations one count per level, got "
                              f"levels={levels!r}, iterations={tuple(iterations)!r}")
        if not (isinstance(finest_stride, int) and finest_stride >= 1):
            raise ConfigError(f"finest_stride must be a positive integer (1: every pixel), got {finest_stride!r}")
        if not (downsample is None or isinstance(downsample, int) and downsample >= 0):
            raise ConfigError(f"downsample must be None (by frame size) or an integer >= 0 (0: full size), got {downsample!r}")
        if not (isinstance(raycast_level, int) and 0 <= raycast_level < levels):
            raise ConfigError(f"raycast_level must be a pyramid level from 0 to {levels - 1}, got {raycast_level!r}")
        if not (isinstance(photometric, (int, float)) and photometric >= 0):
            raise ConfigError(f"photometric must be a weight >= 0 (0: depth alone), got {photometric!r}")
        robust_weights(torch.zeros(1), kernel, kernel_scale)  # an unknown kernel fails here
        self.K, self.mode, self.levels, self.iterations = K, mode, levels, tuple(int(i) for i in iterations)
        self.kernel, self.kernel_scale, self.max_distance = kernel, float(kernel_scale), float(max_distance)
        self.min_cosine = math.cos(math.radians(max_normal_angle))
        self.min_inlier_share, self.max_rmse, self.max_depth = min_inlier_share, max_rmse, max_depth
        self.voxel_size = voxel_size
        self.truncation = 3 * voxel_size if truncation is None else truncation
        self.margin, self.raycast_level, self.smoothing = margin, raycast_level, int(smoothing)
        self.constant_velocity, self.finest_stride = bool(constant_velocity), int(finest_stride)
        self.downsample, self.compiled, self.photometric = downsample, bool(compiled), float(photometric)
        self.K_registered: Tensor | None = None  # K of the registered (downsampled) frames
        self.initial_pose = torch.eye(4, dtype=torch.float64) if initial_pose is None else initial_pose.double()
        self.poses: list[Tensor] = []
        self._volume: TSDFVolume | None = None
        self._unfused: tuple[Tensor, Tensor, Tensor] | None = None  # the last frame (depth, K, pose), fused later
        self._fusing: Future | None = None  # its fusion, run beside the next frame's preparation
        self._executor = ThreadPoolExecutor(1, thread_name_prefix="tsdf-fusion")
        self._previous: Tensor | None = None  # the last frame's depth as registered (downsampled)
        self._previous_grey: list[Tensor] | None = None  # its grey pyramid with derivatives (photometric)
        self.last_fit: FrameFit | None = None  # the last frame's registration

    def _maps(self, depth: Tensor, K: Tensor | None = None, levels: int | None = None, stride: int = 1
              ) -> list[SurfaceMap]:
        K = self.K_registered.to(depth) if K is None else K
        return surface_maps(depth, K, self.levels if levels is None else levels, self.max_distance / 2, stride,
                            self.compiled)

    def _smooth(self, depth: Tensor) -> Tensor:
        return bilateral_filter(depth, self.smoothing) if self.smoothing > 0 else depth

    @property
    def volume(self) -> TSDFVolume | None:
        """The TSDF volume of the frames tracked so far (frame-to-model), None before the first frame."""
        if self._unfused is not None:
            self._fuse(*self._unfused)
            self._unfused = None
        if self._fusing is not None:
            fusing, self._fusing = self._fusing, None
            fusing.result()
        return self._volume

    def _fuse(self, depth: Tensor, K: Tensor, pose: Tensor) -> None:
        frame = DepthFrames(depth[None], K[None], pose.to(depth)[None])
        if self._volume is None:
            points = backproject_depth_to_camera(depth[None], K[None])[0][depth > 0]
            if not len(points):
                raise InputError("the first frame has no valid depth pixel; start the sequence at a frame with depth")
            world = points.double() @ pose[:3, :3].T.to(points.device) + pose[:3, 3].to(points.device)
            bounds = torch.stack([world.amin(0) - self.margin, world.amax(0) + self.margin])
            self._volume = TSDFVolume(bounds, self.voxel_size, self.truncation, sparse=True, device=depth.device,
                                     fusion=FusionSettings(threads=1, compiled=self.compiled))
        self._volume.integrate(frame, progress=False)

    def _model(self, pose: Tensor) -> list[SurfaceMap]:
        """The model's `SurfaceMap`s seen from `pose` (the previous pose), one per level."""
        if self.mode == "frame":
            return self._maps(self._smooth(self._previous))
        guide, K = depth_pyramid(self._previous, self.K_registered.to(self._previous), self.raycast_level + 1,
                                 self.max_distance / 2, self.compiled)[-1]
        depth = raycast_volume(self.volume, guide, K, pose, compiled=self.compiled)
        maps = self._maps(depth, K, self.levels - self.raycast_level)
        return [maps[0]] * self.raycast_level + maps

    def _grey(self, colors: Tensor | None, shape: torch.Size) -> list[Tensor] | None:
        """The grey pyramid of a frame's colours at the registered size (None without the photometric term)."""
        if self.photometric == 0:
            return None
        if colors is None:
            raise InputError("photometric tracking needs the frames' colour images (registered to the depth); "
                             "load them, or set photometric=0 to track depth alone")
        grey = grey_pyramid(grey_levels(float_colors(colors)), self.downsample + 1)[-1]
        if grey.shape != shape:
            raise InputError(f"colour image of {tuple(colors.shape[:2])} pixels for a depth image of another size")
        return grey_pyramid(grey, self.levels)

    def track(self, depth: Tensor, colors: Tensor | None = None) -> Tensor:
        """Register the next depth image Float[Tensor, "h w"] (metres, 0 invalid), with its colour image
        Float[Tensor, "h w 3"] or UInt8 (used when `photometric` > 0), and return its camera-to-world pose
        Float64[Tensor, "4 4"] (CPU); raises TrackingLostError naming the frame."""
        if self._unfused is not None:  # the last frame is fused while this one is prepared
            self._fusing, self._unfused = self._executor.submit(self._fuse, *self._unfused), None
        depth = torch.where(depth <= self.max_depth, depth, 0.0)
        if self.downsample is None:
            self.downsample = int(math.log2(depth.shape[-1] / 320)) if depth.shape[-1] >= 320 else 0
        registered, self.K_registered = depth_pyramid(depth, self.K.to(depth), self.downsample + 1,
                                                      self.max_distance / 2, self.compiled)[-1]
        grey = self._grey(colors.to(depth.device) if colors is not None else None, registered.shape)
        index = len(self.poses)
        if index == 0:
            pose = self.initial_pose.cpu()
            self.last_fit = FrameFit(torch.eye(4, dtype=torch.float64), 1.0, 0.0, False)
        else:
            previous = self.poses[-1]
            source = self._maps(self._smooth(registered), stride=self.finest_stride)
            model = self._model(previous.to(depth.device))  # waits for the last frame's fusion
            motion = torch.eye(4, dtype=torch.float64)
            if self.constant_velocity and index > 1:
                motion = torch.linalg.inv(self.poses[-2]) @ previous
            pair = None if grey is None else GreyPair([grey[0][::self.finest_stride, ::self.finest_stride]]
                                                      + grey[1:], self._previous_grey, self.photometric)
            fit = register_maps(source, model, motion.to(depth.device),
                                self.iterations, self.kernel, self.kernel_scale, self.max_distance, self.min_cosine,
                                self.compiled, pair)
            self.last_fit = fit
            reason = ("the normal equations are degenerate" if fit.degenerate else
                      f"fewer than {self.min_inlier_share:.0%} of its points match the model"
                      if fit.inlier_share < self.min_inlier_share else
                      f"the residual is above {self.max_rmse * 1000:.0f} mm" if fit.rmse > self.max_rmse else None)
            if reason is not None:
                raise TrackingLostError(index, fit.inlier_share, fit.rmse, reason)
            pose = previous @ fit.transform.cpu()
        if self.mode == "model":
            self._unfused = registered, self.K_registered.to(registered), pose
        self._previous = registered
        self._previous_grey = None if grey is None else [with_gradients(level) for level in grey]
        self.poses.append(pose)
        return pose


_COMPILED = {function: CompiledOnCPU(function, "camera tracking")
             for function in (trilinear_tsdf, icp_equations, surface_map, downsample_depth)}


def track_frames(frames: DepthFrames, progress: bool = True, compiled: bool | None = None, **settings) -> Trajectory:
    """Camera poses of depth frames tracked in order (`Tracker(frames.K[0], compiled=..., **settings)`); the frames'
    own `cam_to_world` is not used. Raises TrackingLostError at the first frame that cannot be tracked.
    `compiled`: None compiles on a CPU for sequences of `_COMPILED_FRAMES` frames or more."""
    if not isinstance(frames, DepthFrames):
        raise InputError(f"track_frames needs DepthFrames, got {type(frames).__name__}")
    compiled = len(frames) >= _COMPILED_FRAMES if compiled is None else compiled
    tracker = Tracker(frames.K[0], compiled=compiled, **settings)
    shares, errors = [], []
    start = time.perf_counter()
    for index in progress_bar(range(len(frames)), desc="tracking", unit="frame", enabled=progress):
        tracker.track(frames.depth[index], None if frames.colors is None else frames.colors[index])
        shares.append(tracker.last_fit.inlier_share)
        errors.append(tracker.last_fit.rmse)
    seconds = time.perf_counter() - start
    return Trajectory(torch.stack(tracker.poses), torch.tensor(shares, dtype=torch.float64),
                      torch.tensor(errors, dtype=torch.float64), seconds)


__all__ = [
    "MODES",
    "GreyPair",
    "Tracker",
    "TrackingLostError",
    "Trajectory",
    "bilateral_filter",
    "block_slots",
    "depth_pyramid",
    "downsample_depth",
    "downsample_intrinsics",
    "gauss_newton_step",
    "grey_levels",
    "grey_pyramid",
    "icp_equations",
    "moved_and_projected",
    "photometric_equations",
    "photometric_rows",
    "point_to_plane_rows",
    "point_to_plane_update",
    "projective_matches",
    "raycast_volume",
    "register_maps",
    "surface_map",
    "surface_maps",
    "track_frames",
    "trilinear_tsdf",
    "with_gradients",
]
