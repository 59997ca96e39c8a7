"""The tracker's image pyramids: depth downsampling, camera-frame surface maps (points, normals) per level, grey levels."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property, reduce

import torch
from torch import Tensor

from neuralsurf.cameras import backproject_depth_to_camera, depth_normals
from neuralsurf.devices import CompiledOnCPU


def downsample_depth(depth: Tensor, max_jump: float) -> Tensor:
    """Depth images Float[Tensor, "... h w"] -> Float[Tensor, "... h//2 w//2"]: each 2 x 2 block's mean over
    its valid pixels within `max_jump` metres of the block's nearest valid depth (a block across a
    discontinuity keeps its nearer surface); 0 where the block has no valid pixel."""
    h, w = depth.shape[-2] // 2 * 2, depth.shape[-1] // 2 * 2
    corners = [depth[..., row:h:2, column:w:2] for row in (0, 1) for column in (0, 1)]  # views, no copy
    nearest = reduce(torch.minimum, [torch.where(corner > 0, corner, torch.inf) for corner in corners])
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
    downsample = _COMPILED_DOWNSAMPLE.on(depth.device, compiled)
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
    one_map = _COMPILED_SURFACE_MAP.on(depth.device, compiled)
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


_COMPILED_DOWNSAMPLE, _COMPILED_SURFACE_MAP = (CompiledOnCPU(f, "camera tracking") for f in (downsample_depth, surface_map))
