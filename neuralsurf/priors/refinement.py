"""Completion that keeps what was seen: a prior's field corrected by a smooth residual fitted to the
observed surface, so that the view's data decide where it saw the surface and the prior decides the rest.

The residual r is a dense grid over the extraction box (trilinear), fitted after the prior's own
completion (DeepSDF's latent fit, OccNet's encoding) with the prior frozen:

    g(x) = f(x) / k + r(x)        (k: the median of |grad f| at the observed points, so that g is in
                                   the unit frame's distance whatever the prior's field is: an SDF or logits)

    loss = mean |g(hit)|                                  the observed surface is on the zero level
         + mean relu(-g(free))                            seen empty space is outside (in front of the hits,
                                                          and along rays that hit nothing: the silhouette)
         + mean relu(g(behind))                           just behind a hit is inside
         + smoothness * mean |grad r|^2 + decay * mean r^2   the prior, unchanged, away from the data

The prior's values at the samples are computed once; each step is a grid lookup, so a fit takes a few
seconds on a CPU (4-7 s on the 2-core CPU, loaded, against a minute or more for DeepSDF's latent fit). `view_samples` draws the samples of depth views (`refine_to_view`); a cloud without rays
gives only surface points (`refine_to_cloud`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from neuralsurf.cameras import backproject_depth, box_span, pixel_rays
from neuralsurf.errors import ConfigError, InputError
from neuralsurf.structures import DepthFrames


@dataclass(frozen=True)
class Refinement:
    """Settings of the residual fit (unit-frame distances: a shape's longest side is 1)."""

    resolution: int = 48
    """grid nodes per side of the residual over the extraction box."""
    steps: int = 100
    lr: float = 6e-3
    smoothness: float = 1e-3
    """weight of mean |grad r|^2 (r in distance units, the gradient per unit length)."""
    decay: float = 1.0
    """weight of mean r^2: the residual fades away from the data over about sqrt(smoothness / decay)."""
    free_weight: float = 1.0
    behind_weight: float = 1.0
    behind: float = 0.005
    """how far behind a hit (along its ray) a point is taken to be inside."""
    free_margin: float = 0.004
    """free-space samples stop this far in front of a hit (a few times the depth noise)."""
    free_per_ray: int = 2
    near_free_per_ray: int = 2
    """free-space samples per ray within `near_spread` in front of the hit (the surface's front side)."""
    near_spread: float = 0.03
    empty_per_ray: int = 1
    """free-space samples through the box along each ray without a reading."""
    seed: int = 0

    def __post_init__(self) -> None:
        if self.resolution < 2 or self.steps < 0 or self.lr <= 0:
            raise ConfigError(f"Refinement needs resolution >= 2, steps >= 0 and lr > 0, got resolution="
                              f"{self.resolution}, steps={self.steps}, lr={self.lr}")
        if min(self.smoothness, self.decay, self.free_weight, self.behind_weight, self.behind, self.free_margin,
               self.near_spread) < 0 or min(self.free_per_ray, self.near_free_per_ray, self.empty_per_ray) < 0:
            raise ConfigError("Refinement's weights, distances and sample counts must be >= 0")


DEFAULT_REFINEMENT = Refinement()


@dataclass(frozen=True)
class FitSamples:
    """Where the data say something about the field (unit frame)."""

    surface: Tensor
    """Float[Tensor, "n 3"]: observed surface points (g = 0)."""
    free: Tensor
    """Float[Tensor, "m 3"]: points seen empty (g >= 0)."""
    behind: Tensor
    """Float[Tensor, "b 3"]: points just behind the observed surface (g <= 0)."""


def view_samples(frames: DepthFrames, bounds: Tensor, settings: Refinement = DEFAULT_REFINEMENT) -> FitSamples:
    """The fit samples of depth views in the unit frame: every valid pixel's hit, `behind` past it
    along its ray, and free space in front of it (`free_per_ray` spread from the box's entry to
    `free_margin` before the hit, `near_free_per_ray` within `near_spread` of that); along rays
    without a reading, `empty_per_ray` points through the box (the silhouette's outside).
    bounds: Float[Tensor, "2 3"], the box that holds the shape."""
    if not (frames.depth > 0).any():
        raise InputError("the view has no valid depth pixel: nothing to refine the completion to")
    generator = torch.Generator().manual_seed(settings.seed)
    frames = frames.to("cpu")
    bounds = torch.as_tensor(bounds, dtype=torch.float64)
    depth = frames.depth.double()
    rays = pixel_rays(frames.K.double(), depth.shape[1], depth.shape[2])  # camera frame, z = 1
    pose = frames.cam_to_world.double()
    directions = torch.einsum("nij,nhwj->nhwi", pose[:, :3, :3], rays / rays.norm(dim=-1, keepdim=True))
    origins = pose[:, None, None, :3, 3].expand_as(directions)
    hits = backproject_depth(DepthFrames(frames.depth, frames.K, frames.cam_to_world)).double()
    valid = depth > 0
    distance = (hits - origins).norm(dim=-1)  # along the ray, for valid pixels
    entry, exit_ = box_span(origins.reshape(-1, 3), directions.reshape(-1, 3), bounds)
    entry, exit_ = entry.reshape(valid.shape), exit_.reshape(valid.shape)

    def along(o: Tensor, d: Tensor, start: Tensor, end: Tensor, count: int) -> Tensor:
        if count == 0 or len(o) == 0:
            return o.new_zeros(0, 3)
        u = torch.rand(len(o), count, generator=generator, dtype=o.dtype)
        t = start[:, None] + u * (end - start).clamp_min(0.0)[:, None]
        return (o[:, None] + t[..., None] * d[:, None]).reshape(-1, 3)

    o, d, hit = origins[valid], directions[valid], distance[valid]
    front_end = hit - settings.free_margin
    far = along(o, d, entry[valid], front_end, settings.free_per_ray)
    near = along(o, d, torch.maximum(entry[valid], front_end - settings.near_spread), front_end,
                 settings.near_free_per_ray)
    missed = ~valid & (exit_ > entry)
    empty = along(origins[missed], directions[missed], entry[missed], exit_[missed], settings.empty_per_ray)
    behind = o + (hit + settings.behind)[:, None] * d
    return FitSamples(hits[valid], torch.cat([far, near, empty]), behind)


def cloud_samples(points: Tensor) -> FitSamples:
    """The fit samples of a cloud without rays: its points as the surface, nothing about free space."""
    points = torch.as_tensor(points, dtype=torch.float64)
    if points.ndim != 2 or points.shape[-1] != 3 or not len(points):
        raise InputError(f"refine_to_cloud takes a cloud of shape (n >= 1, 3), got {tuple(points.shape)}")
    empty = points.new_zeros(0, 3)
    return FitSamples(points, empty, empty)


def trilinear_weights(points: Tensor, bounds: Tensor, n: int) -> tuple[Tensor, Tensor]:
    """The 8 nodes (flat indices into an n^3 grid, z, y, x order) and trilinear weights, each
    [m, 8], of points Float[Tensor, "m 3"] in the box Float[Tensor, "2 3"] (clamped to it): a
    lookup is then `(grid.reshape(-1)[nodes] * weights).sum(-1)`."""
    lo, hi = bounds[0].to(points), bounds[1].to(points)
    cell = ((points - lo) / (hi - lo) * (n - 1)).clamp(0, n - 1)
    base = cell.floor().long().clamp(max=n - 2)  # a point on the far face: the last cell, weight 1 at its end
    frac = cell - base
    corners = torch.tensor([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], device=points.device)
    index = base[:, None, :] + corners  # [m, 8, 3] (x, y, z)
    nodes = (index[..., 2] * n + index[..., 1]) * n + index[..., 0]
    weights = torch.where(corners.bool(), frac[:, None, :], 1 - frac[:, None, :]).prod(-1)
    return nodes, weights


def grid_lookup(grid: Tensor, points: Tensor, bounds: Tensor) -> Tensor:
    """Trilinear values [...] of a grid Float[Tensor, "n n n"] (nodes on the box's corners; z, y, x
    axes) at points Float[Tensor, "... 3"] (x, y, z) in the box Float[Tensor, "2 3"] (clamped to it)."""
    nodes, weights = trilinear_weights(points.reshape(-1, 3), bounds, len(grid))
    return (grid.reshape(-1)[nodes] * weights.to(grid.dtype)).sum(-1).reshape(points.shape[:-1])


class ResidualField(nn.Module):
    """x[..., 3] -> base(x) / scale + r(x): a frozen field in distance units plus a residual grid."""

    def __init__(self, base: nn.Module, scale: float, residual: Tensor, bounds: Tensor):
        super().__init__()
        self.base = base
        self.scale = float(scale)
        self.register_buffer("residual", residual.detach().clone(), persistent=False)
        self.register_buffer("bounds", torch.as_tensor(bounds, dtype=torch.float32), persistent=False)

    def forward(self, x: Tensor) -> Tensor:
        base = self.base(x)
        return base / self.scale + grid_lookup(self.residual, x, self.bounds).to(base.dtype)


def field_scale(field: nn.Module, points: Tensor) -> float:
    """The median of |grad field| at points Float[Tensor, "n 3"] (1 for an SDF; an occupancy network's
    logits rise faster), at least 1e-3."""
    x = points.detach().float().clone().requires_grad_(True)
    with torch.enable_grad():
        (gradient,) = torch.autograd.grad(field(x).sum(), x)
    return max(float(gradient.norm(dim=-1).median()), 1e-3)


def smoothness_loss(grid: Tensor, spacing: Tensor) -> Tensor:
    """mean |grad grid|^2 by forward differences, per unit length (spacing: Float[Tensor, "3"] x, y, z)."""
    dz = (grid[1:] - grid[:-1]) / spacing[2]
    dy = (grid[:, 1:] - grid[:, :-1]) / spacing[1]
    dx = (grid[:, :, 1:] - grid[:, :, :-1]) / spacing[0]
    return (dx.pow(2).mean() + dy.pow(2).mean() + dz.pow(2).mean())


def fit_residual(field: nn.Module, samples: FitSamples, bounds: Tensor,
                 settings: Refinement = DEFAULT_REFINEMENT) -> ResidualField:
    """The prior's `field` (frozen; negative inside) plus the residual grid that holds the zero level on
    `samples` (module docstring), over the box Float[Tensor, "2 3"]."""
    device = next(field.parameters()).device
    bounds = torch.as_tensor(bounds, dtype=torch.float32, device=device)
    n = settings.resolution
    grid = torch.zeros(n, n, n, device=device, requires_grad=True)
    spacing = (bounds[1] - bounds[0]) / (n - 1)
    points = {name: getattr(samples, name).float().to(device) for name in ("surface", "free", "behind")}
    scale = field_scale(field, points["surface"])
    with torch.no_grad():
        base = {name: field(p).float() / scale if len(p) else p.new_zeros(0) for name, p in points.items()}
    lookups = {name: trilinear_weights(p, bounds, n) for name, p in points.items()}
    optimizer = torch.optim.Adam([grid], lr=settings.lr)

    def mean(values: Tensor) -> Tensor:
        return values.mean() if values.numel() else values.sum()

    for _ in range(settings.steps):
        flat = grid.reshape(-1)  # the samples' nodes and weights are fixed: `grid_lookup` without recomputing them
        g = {name: base[name] + (flat[nodes] * weights).sum(-1) for name, (nodes, weights) in lookups.items()}
        loss = (mean(g["surface"].abs()) + settings.free_weight * mean(torch.relu(-g["free"]))
                + settings.behind_weight * mean(torch.relu(g["behind"]))
                + settings.smoothness * smoothness_loss(grid, spacing) + settings.decay * grid.pow(2).mean())
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
    if not math.isfinite(float(grid.detach().abs().max())):
        raise InputError("the residual fit diverged (non-finite values): lower Refinement.lr")
    return ResidualField(field, scale, grid.detach(), bounds).eval()


def refine_to_view(field: nn.Module, frames: DepthFrames, bounds: Tensor,
                   settings: Refinement = DEFAULT_REFINEMENT) -> ResidualField:
    """`field` (a prior's completion, unit frame) held to what the depth `frames` saw (`fit_residual`
    on `view_samples`)."""
    return fit_residual(field, view_samples(frames, bounds, settings), bounds, settings)


def refine_to_cloud(field: nn.Module, points: Tensor, bounds: Tensor,
                    settings: Refinement = DEFAULT_REFINEMENT) -> ResidualField:
    """`field` held to the surface points Float[Tensor, "n 3"] of a cloud (no free space)."""
    return fit_residual(field, cloud_samples(points), bounds, settings)
