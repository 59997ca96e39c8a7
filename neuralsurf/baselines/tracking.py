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

Tracking is lost when too few of the frame's points find an inlier (`min_inlier_share`), when their
point-to-plane RMSE is above `max_rmse`, or when the normal equations are degenerate: the tracker raises
`TrackingLostError` naming the frame, instead of fusing it at a wrong pose.

Everything runs on the frames' device (CUDA tensors: CUDA) with vectorised torch ops.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from functools import cached_property

import torch
from torch import Tensor

from neuralsurf.baselines.tsdf import TSDFVolume
from neuralsurf.errors import ConfigError, InputError, NeuralsurfError
from neuralsurf.geometry import _depth_normals, backproject_depth_to_camera
from neuralsurf.progress import progress_bar
from neuralsurf.structures import DepthFrames

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
    blocks = depth[..., :h, :w].unflatten(-1, (w // 2, 2)).unflatten(-3, (h // 2, 2))  # (..., h/2, 2, w/2, 2)
    blocks = blocks.transpose(-3, -2).flatten(-2)  # (..., h/2, w/2, 4)
    valid = blocks > 0
    nearest = torch.where(valid, blocks, torch.inf).amin(-1, keepdim=True)
    use = valid & (blocks - nearest <= max_jump)
    count = use.sum(-1)
    return torch.where(count > 0, (blocks * use).sum(-1) / count.clamp_min(1), 0.0)


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


def depth_pyramid(depth: Tensor, K: Tensor, levels: int, max_jump: float) -> list[tuple[Tensor, Tensor]]:
    """[(depth Float[Tensor, "h_l w_l"], K Float[Tensor, "3 3"])] for levels 0 (the input) to levels - 1,
    each half the size of the one before (`downsample_depth`, `downsample_intrinsics`)."""
    pyramid = [(depth, K)]
    for _ in range(levels - 1):
        depth, K = downsample_depth(depth, max_jump), downsample_intrinsics(K)
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


def surface_maps(depth: Tensor, K: Tensor, levels: int, max_jump: float, stride: int = 1) -> list[SurfaceMap]:
    """`SurfaceMap` of every level of `depth_pyramid(depth Float[Tensor, "h w"], K, levels, max_jump)`;
    normals from image neighbours (`geometry._depth_normals`, discontinuities above 5 % of the depth).
    `stride`: level 0 keeps every stride-th row and column only (a source's points, not a model's pixels)."""
    maps = []
    for level, (level_depth, level_K) in enumerate(depth_pyramid(depth, K, levels, max_jump)):
        points = backproject_depth_to_camera(level_depth[None], level_K[None])
        step = stride if level == 0 else 1
        normals, has = _depth_normals(points, 0.05, step)
        valid = has[0] & (level_depth[::step, ::step] > 0)
        maps.append(SurfaceMap(points[0, ::step, ::step], normals[0], valid, level_K))
    return maps


# ----------------------------------------------------------------------------- raycast


def block_slots(volume: TSDFVolume) -> Tensor:
    """Int64[Tensor, "bx by bz"]: the storage slot of every block of `volume`'s grid, -1 where none is
    allocated (a lookup table for `sample_tsdf`, valid until the volume allocates more blocks)."""
    counts = [int(c) for c in volume.block_counts]
    slots = torch.full(counts, -1, dtype=torch.int64, device=volume.device)
    if volume.sparse:
        slots.view(-1)[volume._keys] = volume._slots
    else:
        slots.view(-1)[: volume._used] = torch.arange(volume._used, device=volume.device)
    return slots


def sample_tsdf(volume: TSDFVolume, slots: Tensor, points: Tensor) -> Tensor:
    """Trilinear interpolation of `volume`'s fused distances at grid coordinates Float[Tensor, "m 3"] (voxel
    units from `volume.origin`) -> Float[Tensor, "m"]; NaN where a corner is unobserved or outside.
    `slots`: `block_slots(volume)`."""
    size = volume.block_size
    (nx, ny, nz), (_, by, bz) = volume.grid_shape, slots.shape
    step = torch.tensor([0, 1], device=points.device)
    base = points.floor()
    fraction = points - base
    base = base.long()
    axes = []  # per axis: (m, 2) indices of the two corners, their inside mask and interpolation weights
    for axis, n in enumerate((nx, ny, nz)):
        index = base[:, axis, None] + step
        t = fraction[:, axis, None]
        axes.append((index.clamp(0, n - 1), (index >= 0) & (index < n), torch.cat([1 - t, t], 1)))
    (i, in_i, w_i), (j, in_j, w_j), (k, in_k, w_k) = axes
    block = ((i[:, :, None, None] // size) * by + (j[:, None, :, None] // size)) * bz + k[:, None, None, :] // size
    local = ((i[:, :, None, None] % size) * size + (j[:, None, :, None] % size)) * size + k[:, None, None, :] % size
    slot = slots.view(-1)[block]  # (m, 2, 2, 2)
    flat = slot.clamp_min(0) * size**3 + local
    inside = in_i[:, :, None, None] & in_j[:, None, :, None] & in_k[:, None, None, :]
    observed = inside & (slot >= 0) & (volume._weight.view(-1)[flat] > 0)
    share = w_i[:, :, None, None] * w_j[:, None, :, None] * w_k[:, None, None, :]
    values = torch.where(observed, volume._tsdf.view(-1)[flat].to(points), torch.nan)
    return (values * share).flatten(1).sum(1)


def raycast_volume(volume: TSDFVolume, guide: Tensor, K: Tensor, cam_to_world: Tensor, steps: int = 1,
                   slots: Tensor | None = None) -> Tensor:
    """Depth of the zero crossing of `volume`'s TSDF seen by a camera, found from a guess of it.

    The fused distances are projective z-differences (`tsdf_voxels`), so along a ray from a camera near
    the fusing ones the surface lies at z + tsdf(z): starting at `guide`, `steps` such updates of z
    (each a trilinear `sample_tsdf`), kept where the last sample was observed and within half the
    truncation of zero (not clipped: the surface is inside the band).

    Args:
        volume: the fused TSDF. guide: Float[Tensor, "h w"] z-depths to start from (0: no ray).
        K: Float[Tensor, "3 3"]; cam_to_world: Float[Tensor, "4 4"] the camera.
        steps: z updates per ray. slots: `block_slots(volume)` (computed when None).
    Returns:
        Float[Tensor, "h w"] z-depth of the surface, 0 where none was found.
    """
    if not (isinstance(steps, int) and steps >= 1):
        raise ConfigError(f"raycast steps must be a positive integer, got {steps!r}")
    slots = block_slots(volume) if slots is None else slots
    rays = backproject_depth_to_camera(torch.ones_like(guide)[None], K[None])[0]  # (h, w, 3), z = 1
    searched = guide > 0
    pose = cam_to_world.to(guide)
    origin = torch.as_tensor(volume.origin, dtype=guide.dtype, device=guide.device)
    grid_rays = rays[searched] @ pose[:3, :3].T / volume.voxel_size  # (m, 3) grid units per unit of z
    start = (pose[:3, 3] - origin) / volume.voxel_size
    z = guide[searched]
    for _ in range(steps):
        value = sample_tsdf(volume, slots, start + z[:, None] * grid_rays)
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


def axis_angle_to_matrix(omega: Tensor) -> Tensor:
    """Rotation matrices Float[Tensor, "... 3 3"] of axis-angle vectors Float[Tensor, "... 3"] (Rodrigues)."""
    angle = omega.norm(dim=-1, keepdim=True)[..., None]  # (..., 1, 1)
    zero = torch.zeros_like(omega[..., 0])
    x, y, z = omega.unbind(-1)
    skew = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], -1).unflatten(-1, (3, 3))
    eye = torch.eye(3, dtype=omega.dtype, device=omega.device).expand_as(skew)
    small = angle < 1e-8
    a = torch.where(small, 1.0, torch.sin(angle) / torch.where(small, 1.0, angle))
    b = torch.where(small, 0.5, (1 - torch.cos(angle)) / torch.where(small, 1.0, angle) ** 2)
    return eye + a * skew + b * skew @ skew


def point_to_plane_update(source: Tensor, target: Tensor, normals: Tensor, weights: Tensor) -> Tensor | None:
    """One Gauss-Newton step Float64[Tensor, "4 4"] of point-to-plane ICP, or None if degenerate.

    Linearises r_i = n_i . (exp(omega) p_i + t - q_i) at omega = 0, t = 0 and solves the weighted 6 x 6
    normal equations (summed in the inputs' dtype, solved in float64) for x = (omega, t); returns [exp(omega) t; 0 1].

    Args:
        source, target, normals: Float[Tensor, "n 3"] matched points p, q and target normals n.
        weights: Float[Tensor, "n"] (0 for rejected pairs).
    """
    residual = ((source - target) * normals).sum(1, keepdim=True)
    rows = torch.cat([torch.linalg.cross(source, normals), normals, residual], 1)  # (n, 7): jacobian | residual
    system = ((rows * weights[:, None]).T @ rows).double()  # (7, 7) in the inputs' dtype, then float64
    hessian, gradient = system[:6, :6], system[:6, 6]
    eigenvalues = torch.linalg.eigvalsh(hessian)
    if not bool(eigenvalues[0] > 1e-9 * eigenvalues[-1].clamp_min(1e-300)):
        return None
    x = -torch.linalg.solve(hessian, gradient)
    matrix = torch.eye(4, dtype=torch.float64, device=source.device)
    matrix[:3, :3], matrix[:3, 3] = axis_angle_to_matrix(x[:3]), x[3:]
    return matrix


@dataclass(frozen=True)
class Matches:
    """Projective correspondences of source points in a model map."""

    source: Tensor
    """Float[Tensor, "n 3"]: source points in the model camera frame."""
    target: Tensor
    """Float[Tensor, "n 3"]: the model point of the pixel each projects to."""
    normals: Tensor
    """Float[Tensor, "n 3"]: the model normal there."""
    inlier: Tensor
    """Bool[Tensor, "n"]: found, within max_distance and with agreeing normals."""


def associate(points: Tensor, normals: Tensor, transform: Tensor, model: SurfaceMap, max_distance: float,
              min_cosine: float) -> Matches:
    """Projective data association: source points Float[Tensor, "n 3"] with normals Float[Tensor, "n 3"]
    (source camera frame), moved by `transform` Float64[Tensor, "4 4"] into the model camera, each matched
    with the model pixel it projects to (nearest)."""
    rotation, translation = transform[:3, :3].to(points), transform[:3, 3].to(points)
    moved = points @ rotation.T + translation
    turned = normals @ rotation.T
    K = model.K.to(points)
    x, y, z = moved.unbind(1)
    inverse_z = 1 / torch.where(z > 0, z, 1.0)
    u = torch.round((K[0, 0] * x + K[0, 1] * y) * inverse_z + K[0, 2])
    v = torch.round(K[1, 1] * y * inverse_z + K[1, 2])
    h, w = model.valid.shape
    inside = (z > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    index = torch.where(inside, v * w + u, 0).long()
    found = inside & model.valid.reshape(-1)[index]
    matched = model.packed[index]  # (n, 6): point, normal
    target, target_normals = matched[:, :3], matched[:, 3:]
    close = (moved - target).square().sum(1) <= max_distance**2
    agree = (turned * target_normals).sum(1) >= min_cosine
    return Matches(moved, target, target_normals, found & close & agree)


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


def register_maps(source: list[SurfaceMap], model: list[SurfaceMap], init: Tensor, iterations: tuple[int, ...],
                  kernel: str, kernel_scale: float, max_distance: float, min_cosine: float) -> FrameFit:
    """Point-to-plane ICP of a source pyramid onto a model pyramid (lists finest first, same length),
    coarse to fine from `init` Float64[Tensor, "4 4"] (source camera -> model camera); `iterations[l]`
    Gauss-Newton steps at level l (finest first)."""
    transform = init.double().clone()
    degenerate = False
    for level in reversed(range(len(source))):
        src, valid = source[level], source[level].valid
        points, normals = src.points[valid], src.normals[valid]
        for _ in range(iterations[level]):
            matches = associate(points, normals, transform, model[level], max_distance, min_cosine)
            residual = ((matches.source - matches.target) * matches.normals).sum(1)
            weights = robust_weights(residual, kernel, kernel_scale) * matches.inlier  # rejected pairs weigh 0
            update = None if int(matches.inlier.sum()) < 6 else point_to_plane_update(
                matches.source, matches.target, matches.normals, weights)
            degenerate = update is None
            if degenerate:
                break
            transform = update @ transform
            if float(update[:3, 3].norm()) < 1e-4 and float((update[:3, :3].diagonal().sum() - 1) / 2) > 1 - 5e-9:
                break  # converged: the step moved less than 0.1 mm and turned less than 1e-4 rad
    finest = source[0]
    points, normals = finest.points[finest.valid], finest.normals[finest.valid]
    matches = associate(points, normals, transform, model[0], max_distance, min_cosine)
    residual = ((matches.source - matches.target) * matches.normals).sum(1)[matches.inlier]
    share = float(matches.inlier.sum()) / max(len(points), 1)
    rmse = float(residual.square().mean().sqrt()) if len(residual) else math.inf
    return FrameFit(transform, share, rmse, degenerate)


# ----------------------------------------------------------------------------- tracker


class Tracker:
    """Tracks depth frames one at a time (see the module docstring); `track(depth)` returns the pose.

    Args:
        K: Float[Tensor, "3 3"] intrinsics of every frame.
        mode: "model" (frame-to-model against the fused TSDF) or "frame" (frame-to-frame).
        levels: pyramid levels (level 0 the full image).
        iterations: Gauss-Newton steps per level, finest first (one per level).
        kernel, kernel_scale: robust kernel ("huber", "tukey", "none") and its scale in metres.
        max_distance: correspondences further apart (metres) are rejected.
        max_normal_angle: correspondences whose normals differ by more (degrees) are rejected.
        min_inlier_share, max_rmse: below / above these a frame is lost (`TrackingLostError`).
        max_depth: readings beyond this (metres) are ignored (tracking and fusion).
        voxel_size, truncation: the TSDF volume of mode "model" (metres; truncation default 3 voxels).
        margin: the volume's box is the first frame's points grown by this (metres) in every direction.
        initial_pose: Float[Tensor, "4 4"] pose of the first frame (default identity).
        raycast_level: the pyramid level at which the model is raycast (0: full size; coarser is faster, and
            its coarser levels are downsampled from it; finer source levels associate with it).
        smoothing: radius (pixels) of the `bilateral_filter` of the depth that is registered (0: none).
        constant_velocity: start each frame's ICP from the previous frame's motion repeated (else from
            the previous pose, as KinectFusion).
        finest_stride: the finest level registers every finest_stride-th row and column of the frame
            (1: every pixel, as KinectFusion; 2, the default, is about 4 times cheaper there and tracked
            livingroom1 and redkitchen to the same ATE).
    """

    def __init__(self, K: Tensor, mode: str = "model", levels: int = 3, iterations: tuple[int, ...] = (4, 5, 10),
                 kernel: str = "huber", kernel_scale: float = 0.01, max_distance: float = 0.1,
                 max_normal_angle: float = 30.0, min_inlier_share: float = 0.3, max_rmse: float = 0.03,
                 max_depth: float = 4.0, voxel_size: float = 0.02, truncation: float | None = None,
                 margin: float = 3.0, initial_pose: Tensor | None = None, raycast_level: int = 1,
                 smoothing: int = 1, constant_velocity: bool = True, finest_stride: int = 2):
        if mode not in MODES:
            raise ConfigError(f"tracking mode must be one of {MODES}, got {mode!r}")
        if not (isinstance(levels, int) and levels >= 1) or len(iterations) != levels:
            raise ConfigError(f"levels must be a positive integer and iterations one count per level, got "
                              f"levels={levels!r}, iterations={tuple(iterations)!r}")
        if not (isinstance(finest_stride, int) and finest_stride >= 1):
            raise ConfigError(f"finest_stride must be a positive integer (1: every pixel), got {finest_stride!r}")
        if not (isinstance(raycast_level, int) and 0 <= raycast_level < levels):
            raise ConfigError(f"raycast_level must be a pyramid level from 0 to {levels - 1}, got {raycast_level!r}")
        robust_weights(torch.zeros(1), kernel, kernel_scale)  # an unknown kernel fails here
        self.K, self.mode, self.levels, self.iterations = K, mode, levels, tuple(int(i) for i in iterations)
        self.kernel, self.kernel_scale, self.max_distance = kernel, float(kernel_scale), float(max_distance)
        self.min_cosine = math.cos(math.radians(max_normal_angle))
        self.min_inlier_share, self.max_rmse, self.max_depth = min_inlier_share, max_rmse, max_depth
        self.voxel_size = voxel_size
        self.truncation = 3 * voxel_size if truncation is None else truncation
        self.margin, self.raycast_level, self.smoothing = margin, raycast_level, int(smoothing)
        self.constant_velocity, self.finest_stride = bool(constant_velocity), int(finest_stride)
        self.initial_pose = torch.eye(4, dtype=torch.float64) if initial_pose is None else initial_pose.double()
        self.poses: list[Tensor] = []
        self.volume: TSDFVolume | None = None
        self._previous: Tensor | None = None  # the last frame's depth (h, w)
        self.last_fit: FrameFit | None = None  # the last frame's registration

    def _maps(self, depth: Tensor, K: Tensor | None = None, levels: int | None = None, stride: int = 1
              ) -> list[SurfaceMap]:
        K = self.K.to(depth) if K is None else K
        return surface_maps(depth, K, self.levels if levels is None else levels, self.max_distance / 2, stride)

    def _smooth(self, depth: Tensor) -> Tensor:
        return bilateral_filter(depth, self.smoothing) if self.smoothing > 0 else depth

    def _fuse(self, depth: Tensor, pose: Tensor) -> None:
        frame = DepthFrames(depth[None], self.K.to(depth)[None], pose.to(depth)[None])
        if self.volume is None:
            points = backproject_depth_to_camera(depth[None], self.K.to(depth)[None])[0][depth > 0]
            if not len(points):
                raise InputError("the first frame has no valid depth pixel; start the sequence at a frame with depth")
            world = points.double() @ pose[:3, :3].T.to(points.device) + pose[:3, 3].to(points.device)
            bounds = torch.stack([world.amin(0) - self.margin, world.amax(0) + self.margin])
            self.volume = TSDFVolume(bounds, self.voxel_size, self.truncation, device=depth.device, sparse=True,
                                     threads=1, compiled=False)
        self.volume.integrate(frame, progress=False)

    def _model(self, pose: Tensor) -> list[SurfaceMap]:
        """The model's `SurfaceMap`s seen from `pose` (the previous pose), one per level."""
        if self.mode == "frame":
            return self._maps(self._smooth(self._previous))
        guide, K = depth_pyramid(self._previous, self.K.to(self._previous), self.raycast_level + 1,
                                 self.max_distance / 2)[-1]
        maps = self._maps(raycast_volume(self.volume, guide, K, pose), K, self.levels - self.raycast_level)
        return [maps[0]] * self.raycast_level + maps

    def track(self, depth: Tensor) -> Tensor:
        """Register the next depth image Float[Tensor, "h w"] (metres, 0 invalid) and return its
        camera-to-world pose Float64[Tensor, "4 4"] (CPU); raises TrackingLostError naming the frame."""
        depth = torch.where(depth <= self.max_depth, depth, 0.0)
        index = len(self.poses)
        if index == 0:
            pose = self.initial_pose.cpu()
            self.last_fit = FrameFit(torch.eye(4, dtype=torch.float64), 1.0, 0.0, False)
        else:
            previous = self.poses[-1]
            model = self._model(previous.to(depth.device))
            source = self._maps(self._smooth(depth), stride=self.finest_stride)
            motion = torch.eye(4, dtype=torch.float64)
            if self.constant_velocity and index > 1:
                motion = torch.linalg.inv(self.poses[-2]) @ previous
            fit = register_maps(source, model, motion.to(depth.device),
                                self.iterations, self.kernel, self.kernel_scale, self.max_distance, self.min_cosine)
            self.last_fit = fit
            reason = ("the normal equations are degenerate" if fit.degenerate else
                      f"fewer than {self.min_inlier_share:.0%} of its points match the model"
                      if fit.inlier_share < self.min_inlier_share else
                      f"the residual is above {self.max_rmse * 1000:.0f} mm" if fit.rmse > self.max_rmse else None)
            if reason is not None:
                raise TrackingLostError(index, fit.inlier_share, fit.rmse, reason)
            pose = previous @ fit.transform.cpu()
        if self.mode == "model":
            self._fuse(depth, pose)
        self._previous = depth
        self.poses.append(pose)
        return pose


def track_frames(frames: DepthFrames, progress: bool = True, **settings) -> Trajectory:
    """Camera poses of depth frames tracked in order (`Tracker(frames.K[0], **settings)`); the frames'
    own `cam_to_world` is not used. Raises TrackingLostError at the first frame that cannot be tracked."""
    if not isinstance(frames, DepthFrames):
        raise InputError(f"track_frames needs DepthFrames, got {type(frames).__name__}")
    tracker = Tracker(frames.K[0], **settings)
    shares, errors = [], []
    start = time.perf_counter()
    for depth in progress_bar(frames.depth, desc="tracking", unit="frame", enabled=progress):
        tracker.track(depth)
        shares.append(tracker.last_fit.inlier_share)
        errors.append(tracker.last_fit.rmse)
    seconds = time.perf_counter() - start
    return Trajectory(torch.stack(tracker.poses), torch.tensor(shares, dtype=torch.float64),
                      torch.tensor(errors, dtype=torch.float64), seconds)


__all__ = [
    "MODES",
    "Tracker",
    "TrackingLostError",
    "Trajectory",
    "bilateral_filter",
    "block_slots",
    "depth_pyramid",
    "downsample_depth",
    "downsample_intrinsics",
    "point_to_plane_update",
    "raycast_volume",
    "register_maps",
    "sample_tsdf",
    "track_frames",
]
