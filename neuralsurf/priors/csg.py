"""Signed distances of primitives and their CSG: pure functions of float64 points.

Every primitive is exact (the Euclidean distance to its surface, negative inside; Quilez's
formulas). Their union (min), intersection (max) and difference (max(a, -b)) have the exact zero
set and the exact sign everywhere, and the exact distance outside a union; elsewhere the value is a
lower bound on the distance (off by at most the distance to the nearest seam between parts). So the
occupancy labels and surface of a CSG shape are exact, and SDF samples near its surface are exact
except within their own distance of a seam.

The up axis is y (shapes stand on the x-z plane). All functions take p: Float64[Tensor, "... 3"]
and return Float64[Tensor, "..."].
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor


def _offset(p: Tensor, center: Sequence[float]) -> Tensor:
    return p - torch.as_tensor(center, dtype=p.dtype, device=p.device)


def _length(v: Tensor) -> Tensor:
    """|v| over the last axis, with a finite gradient at v = 0 (points exactly on a surface)."""
    return (v.square().sum(-1) + torch.finfo(v.dtype).tiny).sqrt()


def sphere(p: Tensor, center: Sequence[float], radius: float) -> Tensor:
    """Sphere of `radius` around `center`."""
    return _length(_offset(p, center)) - radius


def box(p: Tensor, center: Sequence[float], half: Sequence[float], rounding: float = 0.0) -> Tensor:
    """Axis-aligned box of half-extents `half` around `center`, its edges rounded by `rounding`
    (the outer size stays `half`; rounding <= min(half))."""
    half = torch.as_tensor(half, dtype=p.dtype, device=p.device) - rounding
    q = _offset(p, center).abs() - half
    return _length(q.clamp_min(0)) + q.amax(-1).clamp_max(0) - rounding


def cylinder(p: Tensor, center: Sequence[float], radius: float, half_height: float) -> Tensor:
    """Capped cylinder with axis y: |x-z offset| <= radius, |y offset| <= half_height."""
    q = _offset(p, center)
    d = torch.stack([_length(q[..., [0, 2]]) - radius, q[..., 1].abs() - half_height], dim=-1)
    return _length(d.clamp_min(0)) + d.amax(-1).clamp_max(0)


def capped_cone(p: Tensor, center: Sequence[float], half_height: float, bottom_radius: float,
                top_radius: float) -> Tensor:
    """Truncated cone with axis y: radius `bottom_radius` at y = -half_height, `top_radius` at
    y = +half_height (relative to `center`)."""
    q = _offset(p, center)
    r = _length(q[..., [0, 2]])
    y = q[..., 1]
    h, r1, r2 = half_height, bottom_radius, top_radius
    k2x, k2y = r2 - r1, 2.0 * h
    ca_x = r - torch.minimum(r, torch.where(y < 0, torch.full_like(r, r1), torch.full_like(r, r2)))
    ca_y = y.abs() - h
    t = (((r2 - r) * k2x + (h - y) * k2y) / (k2x**2 + k2y**2)).clamp(0.0, 1.0)
    cb_x = r - r2 + k2x * t
    cb_y = y - h + k2y * t
    sign = torch.where((cb_x < 0) & (ca_y < 0), -1.0, 1.0).to(p)
    return sign * (torch.minimum(ca_x**2 + ca_y**2, cb_x**2 + cb_y**2) + torch.finfo(p.dtype).tiny).sqrt()


def torus_z(p: Tensor, center: Sequence[float], major: float, minor: float) -> Tensor:
    """Torus around the z axis through `center` (its ring lies in the x-y plane): a tube of radius
    `minor` at distance `major` from the axis."""
    q = _offset(p, center)
    ring = _length(q[..., :2]) - major
    return _length(torch.stack([ring, q[..., 2]], dim=-1)) - minor


def union(*distances: Tensor) -> Tensor:
    """min over parts: inside any of them."""
    return torch.stack(torch.broadcast_tensors(*distances)).amin(0)


def intersection(*distances: Tensor) -> Tensor:
    """max over parts: inside all of them."""
    return torch.stack(torch.broadcast_tensors(*distances)).amax(0)


def difference(a: Tensor, b: Tensor) -> Tensor:
    """Inside `a` and outside `b`."""
    return torch.maximum(a, -b)
