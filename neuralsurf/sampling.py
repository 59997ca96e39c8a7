"""Training samples for SDF fitting, built from a point cloud alone, in the unit frame.

Three kinds of samples (DeepSDF, IGR): surface points (with normals when known), near-surface
points (the surface jittered by Gaussian noise) and free-space points (uniform in the box). Near
and free points get an approximate signed distance from their nearest cloud point and its normal;
away from the cloud, free points take their sign from the cloud's generalised winding number
instead, which a patch of wrongly oriented normals (noisy or thin parts) cannot flip.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from neuralsurf.errors import InputError
from neuralsurf.geometry import cloud_spacing, cloud_winding_number, knn, point_areas
from neuralsurf.structures import PointCloud


def approximate_sdf(query: Tensor, points: Tensor, normals: Tensor, spacing: float) -> Tensor:
    """Signed distance estimated from the nearest oriented cloud point p with normal n.

    Close to the surface (|x - p| < 2 spacing) the point-to-plane distance n.(x - p) is used, which
    is exact to second order; farther away, |x - p| with the sign of n.(x - p), which is exact
    when p is the true closest point and avoids the plane's underestimate.

    Args:
        query: Float[Tensor, "m 3"]; points, normals: Float[Tensor, "n 3"] (unit, outward);
        spacing: typical distance between neighbouring cloud points.
    Returns:
        Float[Tensor, "m"].
    """
    distance, index = knn(query, points, 1)
    distance, index = distance[:, 0], index[:, 0]
    plane = ((query - points[index]) * normals[index]).sum(-1)
    return torch.where(distance < 2 * spacing, plane, torch.sign(plane) * distance)


def winding_signs(
    query: Tensor, points: Tensor, normals: Tensor, n_points: int, seed: int = 0, distance: Tensor | None = None
) -> tuple[Tensor, float]:
    """Inside / outside of query points by the winding number of a random subsample of the cloud.

    Args:
        query: Float[Tensor, "m 3"]; points, normals: Float[Tensor, "n 3"] (unit, outward);
        n_points: size of the subsample (the cost is m x n_points); seed: its draw;
        distance: Float[Tensor, "m"], the queries' distances to the cloud: if given, only those beyond the
            reach are read (the others get sign 0).
    Returns:
        sign Float[Tensor, "m"]: +1 outside (w < 1/2), -1 inside; reach: the distance from the cloud
        beyond which the sign is reliable (3 subsample spacings).
    """
    pick = torch.randperm(len(points), generator=torch.Generator().manual_seed(seed))[:n_points]
    subsample, sub_normals = points[pick], normals[pick]
    reach = 3 * cloud_spacing(subsample) if len(subsample) > 1 else math.inf
    read = slice(None) if distance is None else (distance > reach).nonzero()[:, 0]
    # a CPU: (chunk, n_points) buffers of ~1.3 MB, which stay in cache (64 rows of 5,000 points: 2x
    # faster than 512); a GPU: its width
    chunk = max(16, 320_000 // len(subsample)) if query.device.type == "cpu" else 16_384
    winding = cloud_winding_number(query[read], subsample, sub_normals, point_areas(subsample), chunk=chunk)
    sign = torch.zeros(len(query), dtype=query.dtype, device=query.device)
    sign[read] = torch.where(winding < 0.5, 1.0, -1.0).to(sign)
    return sign, reach


def held_out_split(count: int, share: float, seed: int) -> tuple[Tensor, Tensor]:
    """(held out, kept): Long[Tensor] indices of `count` points, a random `share` of them held out (`seed`), the
    same for the same arguments: the fit's held-out points and the mesh's (`snapping`) are one set."""
    order = torch.randperm(count, generator=torch.Generator().manual_seed(seed))
    split = int(share * count)
    return order[:split], order[split:]


@dataclass(frozen=True)
class SDFSamples:
    """A pool of training samples in the unit frame, drawn once per fit."""

    surface_points: Tensor
    """Float[Tensor, "n 3"]: the input cloud."""
    surface_normals: Tensor | None
    """Float[Tensor, "n 3"] | None: its outward unit normals, when known or estimated."""
    near_points: Tensor
    """Float[Tensor, "m 3"]: surface points plus Gaussian noise."""
    free_points: Tensor
    """Float[Tensor, "k 3"]: uniform in the box [-box, box]^3."""
    near_sdf: Tensor | None
    """Float[Tensor, "m"] | None: approximate signed distance of near points (needs normals)."""
    free_sdf: Tensor | None
    """Float[Tensor, "k"] | None: approximate signed distance of free points (needs normals)."""

    def to(self, device: torch.device | str) -> SDFSamples:
        move = lambda t: None if t is None else t.to(device)  # noqa: E731
        return type(self)(*(move(getattr(self, name)) for name in self.__dataclass_fields__))


def make_sdf_samples(
    cloud: PointCloud,
    n_near: int = 1_000_000,
    n_free: int = 250_000,
    near_sigmas: tuple[float, ...] = (0.0025, 0.025),
    box: float = 0.55,
    winding_points: int = 5000,
    seed: int = 0,
    device: torch.device | str = "cpu",
) -> SDFSamples:
    """Build the sample pool of a unit-frame cloud (see `Normalization.cloud_to_unit`) on `device`:
    the random draws are made on the CPU (the same pool on every device), the distances and winding
    numbers where the pool will live (on an H100 the bunny's eager 400-step fit: 7.0 s with the pool built
    on the CPU, 5.1 s with it built on the GPU by brute-force `knn`).

    Near points are split evenly between the Gaussian standard deviations `near_sigmas`. Free points
    far from the cloud take their sign from the winding number of `winding_points` cloud points
    (`winding_signs`; 0 = always the nearest normal's sign): on the noisy bunny (20k points, 0.5 %
    noise, estimated normals) the nearest normal gives 4.5 % of them the wrong sign, which the fit
    turns into surfaces floating in free space; the winding number none.
    """
    if n_near < 1 or n_free < 1 or not near_sigmas or min(near_sigmas) <= 0:
        raise InputError(
            f"sampling needs n_near, n_free >= 1 and positive near_sigmas, got n_near={n_near}, "
            f"n_free={n_free}, near_sigmas={near_sigmas}"
        )
    if not (isinstance(winding_points, int) and winding_points >= 0):
        raise InputError(f"winding_points must be an integer >= 0 (0 = off), got {winding_points!r}")
    generator = torch.Generator().manual_seed(seed)
    points = cloud.points.detach().cpu().float()
    normals = None if cloud.normals is None else cloud.normals.detach().cpu().float()
    anchor = torch.randint(len(points), (n_near,), generator=generator)
    sigma = torch.tensor(near_sigmas)[torch.arange(n_near) % len(near_sigmas)]
    near = points[anchor] + sigma[:, None] * torch.randn(n_near, 3, generator=generator)
    free = (2 * torch.rand(n_free, 3, generator=generator) - 1) * box
    points, near, free = points.to(device), near.to(device), free.to(device)
    normals = None if normals is None else normals.to(device)
    near_sdf = free_sdf = None
    if normals is not None:
        spacing = cloud_spacing(points) if len(points) > 1 else 0.0
        near_sdf = approximate_sdf(near, points, normals, spacing)
        free_sdf = signed_distance(free, points, normals, spacing, winding_points, seed)
    return SDFSamples(points, normals, near, free, near_sdf, free_sdf)


def signed_distance(query: Tensor, points: Tensor, normals: Tensor, spacing: float, winding_points: int = 5000,
                    seed: int = 0) -> Tensor:
    """Float[Tensor, "m"]: `approximate_sdf` of Float[Tensor, "m 3"] queries anywhere in the box, its sign taken
    from the winding number of `winding_points` cloud points (`winding_signs`; 0: the nearest normal's) where the
    query lies beyond that sign's reach."""
    sdf = approximate_sdf(query, points, normals, spacing)
    if winding_points > 0:  # beyond 2 spacings |sdf| is the distance to the cloud
        distance = sdf.abs()
        sign, reach = winding_signs(query, points, normals, winding_points, seed, distance)
        sdf = torch.where(distance > reach, sign * distance, sdf)
    return sdf


@dataclass(frozen=True)
class SDFBatch(SDFSamples):
    """One training batch, drawn from `SDFSamples` (its fields, fewer rows)."""


def draw_batch(samples: SDFSamples, batch_size: int, free_fraction: float, generator: torch.Generator) -> SDFBatch:
    """`batch_size` surface and near points and `free_fraction * batch_size` free points, at random.

    Indices are drawn on the CPU with `generator` (so a resumed run draws the same batches) and the
    rows are gathered on the samples' device.
    """
    device = samples.surface_points.device

    def pick(n_total: int, n: int) -> Tensor:
        return torch.randint(n_total, (n,), generator=generator).to(device)

    take = lambda t, i: None if t is None else t[i]  # noqa: E731
    s = pick(len(samples.surface_points), batch_size)
    m = pick(len(samples.near_points), batch_size)
    f = pick(len(samples.free_points), max(1, int(free_fraction * batch_size)))
    return SDFBatch(
        samples.surface_points[s],
        take(samples.surface_normals, s),
        samples.near_points[m],
        samples.free_points[f],
        take(samples.near_sdf, m),
        take(samples.free_sdf, f),
    )
