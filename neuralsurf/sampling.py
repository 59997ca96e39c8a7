"""Training samples for SDF fitting, built from a point cloud alone, in the unit frame.

Three kinds of samples (DeepSDF, IGR): surface points (with normals when known), near-surface
points (the surface jittered by Gaussian noise) and free-space points (uniform in the box). Near
and free points get an approximate signed distance from their nearest cloud point and its normal.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from neuralsurf.errors import InputError
from neuralsurf.geometry import knn
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


def cloud_spacing(points: Tensor) -> float:
    """Median distance from a point to its nearest other point. points: Float[Tensor, "n 3"]."""
    distance, _ = knn(points, points, 2)
    return float(distance[:, 1].median())


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
        return SDFSamples(*(move(getattr(self, name)) for name in self.__dataclass_fields__))


def make_sdf_samples(
    cloud: PointCloud,
    n_near: int = 1_000_000,
    n_free: int = 250_000,
    near_sigmas: tuple[float, ...] = (0.0025, 0.025),
    box: float = 0.55,
    seed: int = 0,
) -> SDFSamples:
    """Build the sample pool of a unit-frame cloud (see `Normalization.cloud_to_unit`).

    Near points are split evenly between the Gaussian standard deviations `near_sigmas`.
    """
    if n_near < 1 or n_free < 1 or not near_sigmas or min(near_sigmas) <= 0:
        raise InputError(
            f"sampling needs n_near, n_free >= 1 and positive near_sigmas, got n_near={n_near}, "
            f"n_free={n_free}, near_sigmas={near_sigmas}"
        )
    generator = torch.Generator().manual_seed(seed)
    points = cloud.points.detach().cpu().float()
    normals = None if cloud.normals is None else cloud.normals.detach().cpu().float()
    anchor = torch.randint(len(points), (n_near,), generator=generator)
    sigma = torch.tensor(near_sigmas)[torch.arange(n_near) % len(near_sigmas)]
    near = points[anchor] + sigma[:, None] * torch.randn(n_near, 3, generator=generator)
    free = (2 * torch.rand(n_free, 3, generator=generator) - 1) * box
    near_sdf = free_sdf = None
    if normals is not None:
        spacing = cloud_spacing(points) if len(points) > 1 else 0.0
        near_sdf = approximate_sdf(near, points, normals, spacing)
        free_sdf = approximate_sdf(free, points, normals, spacing)
    return SDFSamples(points, normals, near, free, near_sdf, free_sdf)


@dataclass(frozen=True)
class SDFBatch:
    """One training batch, drawn from `SDFSamples` (fields as there, fewer rows)."""

    surface_points: Tensor
    surface_normals: Tensor | None
    near_points: Tensor
    free_points: Tensor
    near_sdf: Tensor | None
    free_sdf: Tensor | None


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
