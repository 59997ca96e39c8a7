"""The tracker: frame-to-model (raycast of the fused TSDF) or frame-to-frame, one frame at a time."""

from __future__ import annotations

import math
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import torch
from torch import Tensor

from neuralsurf.baselines.tracking.alignment import FrameFit, GreyPair, register_maps, robust_weights
from neuralsurf.baselines.tracking.maps import (
    SurfaceMap,
    bilateral_filter,
    depth_pyramid,
    grey_levels,
    grey_pyramid,
    surface_maps,
    with_gradients,
)
from neuralsurf.baselines.tsdf import FusionSettings, TSDFVolume
from neuralsurf.cameras import backproject_depth_to_camera, pixel_rays
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
    sample = _COMPILED_SAMPLING.on(guide.device, compiled)
    for _ in range(steps):
        value = sample(volume._tsdf, volume._weight, slots, start + z[:, None] * grid_rays, volume.block_size,
                       volume.grid_shape)
        z = z + torch.nan_to_num(value)
    depth = torch.zeros_like(guide)
    depth[searched] = torch.where(value.abs() < volume.truncation / 2, z, 0.0)  # NaN compares False
    return depth


_COMPILED_SAMPLING = CompiledOnCPU(trilinear_tsdf, "camera tracking")


# ----------------------------------------------------------------------------- tracker


_COMPILED_FRAMES = 500
"""track_frames(compiled=None) compiles the tracker's loops on a CPU for sequences of this many frames or more.
Measured on the 2-core CPU (benchmarks/bench_tracking.py): compiling took 16 s from torch's on-disk cache and
about 45 s without it; compiled frames took 30 ms (livingroom1) and 40 ms (redkitchen) less wall time than eager
ones, so compiling pays from about five hundred frames on."""


class Tracker:
    """Tracks depth frames one at a time (see `neuralsurf.baselines.tracking`); `track(depth)` returns the pose.

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
        compiled: on a CPU, run the raycast's volume sampling, the ICP iterations, the pyramids' downsampling and
            surface maps and the fusion through torch.compile: about 40 % less wall time a frame after a
            compilation of 16 s (from torch's on-disk cache) to 45 s.
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
        if self._fusing is not None:  # frames are fused in order: the one on the second thread first
            fusing, self._fusing = self._fusing, None
            fusing.result()
        if self._unfused is not None:
            unfused, self._unfused = self._unfused, None
            self._fuse(*unfused)
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
