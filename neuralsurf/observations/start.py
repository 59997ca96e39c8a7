"""A closed-form start for a fit to oriented points: a voxel SDF solved in one least-squares step.

The grid covers the fit's box [-box, box]^3 (unit frame) with `resolution` cells per side. Its values begin as
signed distances to the cloud: on a grid `coarse` times coarser everywhere (`sampling.signed_distance`, with the
sign of the cloud's winding number far from it), interpolated, and within `band` cells of a point the distance to
the nearest point's tangent plane (`plane_distance`: the median of several off sharp edges). Then every point p with normal n asks f(p) = 0 and f(p +- h n) = +-h
(h: one voxel), in one least-squares solve (`models.grid.solve_values`, the one the room fit solves from depth
rays) with a membrane term over the grid: within a coarse cell of the points every value is an unknown that follows
its neighbours as well as its start, so where overlapping scans lie slightly out of register (the nearest plane
changes side between them), or a patch of normals is flipped, or the interpolated coarse field crosses zero near
the surface, the surface stays one and its side is what its surroundings say, not what one plane says (with
smoothness 0 the merged Stanford scans' start falls into 502 pieces, with it one). On a smooth clean surface the
membrane biases the values toward their neighbours' mean; given points held out of the equations, the solve is
refined while they come closer to its zero level, and the values it moved by less than a tenth of a voxel go back
to their plane distances (none changes its sign), which takes that bias back where it is what limits the start
(docs/benchmarks.md). A network then only refines this field (`models.RefinedSDF`).
"""

from __future__ import annotations

import torch
from torch import Tensor

from neuralsurf.errors import ConfigError, InputError
from neuralsurf.geometry import cloud_spacing, knn, take_rows
from neuralsurf.models.grid import VoxelSDF, solve_values
from neuralsurf.sampling import signed_distance

REFINE_BELOW = 0.1
"""`voxel_start` refines its solve only where the held-out points' mean |f| starts below this many voxels."""

KEEP_START = 0.1
"""On a cloud that passes `REFINE_BELOW`, each value the solve moved by less than this many voxels goes back to its
start (the plane distances), and by more is moved back this far, where that brings the held-out points closer;
values whose start has the other sign keep the solve's."""


def grid_points(counts: int, origin: float, step: float) -> Tensor:
    """Float[Tensor, "counts^3 3"]: the points origin + (i, j, k) * step of a cubic grid, i-major."""
    axis = origin + torch.arange(counts, dtype=torch.float64) * step
    return torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3).float()


def band_points(points: Tensor, origin: float, voxel: float, resolution: int, band: int) -> Tensor:
    """Long[Tensor, "k 3"]: the indices of the grid points (resolution + 1 per side, spaced `voxel` from
    `origin`) that are corners of cells within `band` cells of a cell holding one of Float[Tensor, "n 3"]
    `points`."""
    cells = ((points.double() - origin) / voxel).floor().long().clamp(0, resolution - 1)
    near = torch.zeros((resolution + 1,) * 3, dtype=torch.bool, device=points.device)  # cells, then their corners
    near[cells[:, 0], cells[:, 1], cells[:, 2]] = True
    size = resolution + 1
    for axis in range(3):  # dilated by `band` cells either way, then to the far corners: separable shifts
        grown = near.clone()
        for shift in range(1, band + 2):
            grown.narrow(axis, shift, size - shift).logical_or_(near.narrow(axis, 0, size - shift))
        for shift in range(1, band + 1):
            grown.narrow(axis, 0, size - shift).logical_or_(near.narrow(axis, shift, size - shift))
        near = grown
    return near.nonzero()


def plane_distance(query: Tensor, points: Tensor, normals: Tensor, reach: float, k: int = 8) -> Tensor:
    """Float[Tensor, "m"]: the signed distance of Float[Tensor, "m 3"] queries to the tangent plane of their
    nearest point (Float[Tensor, "n 3"] points, unit normals), or, for a query farther than `reach` from it, the
    median over its `k` nearest points' planes (all, when fewer). Near a smooth surface a plane errs by the
    curvature times the squared distance along it, where the distance to the point errs by the gaps between the
    points (on the bunny's 100k points the start's exact Chamfer-L1 is 3.6e-5 with planes, 9.4e-5 with distances
    beyond two voxels); a few voxels off a sharp edge the nearest point may lie on the other face, whose plane
    passes on the wrong side: the median of several planes keeps the side."""
    distance, index = knn(query, points, 1, within=reach)  # no farther: 1.8x faster on the bunny's band
    nearest = index[:, 0].clamp_max(len(points) - 1)
    plane = ((query - take_rows(points, nearest)) * take_rows(normals, nearest)).sum(-1)
    far = distance[:, 0].isinf().nonzero()[:, 0]
    if len(far):
        _, index = knn(query[far], points, min(k, len(points)))
        planes = ((query[far, None] - take_rows(points, index)) * take_rows(normals, index)).sum(-1)
        plane[far] = planes.median(-1).values
    return plane


def point_equations(points: Tensor, normals: Tensor, offset: float) -> tuple[Tensor, Tensor, Tensor]:
    """What oriented points say about an SDF: f(p) = 0 and f(p +- offset n) = +-offset, for Float[Tensor, "n 3"]
    points and unit normals. Returns (points Float[Tensor, "3n 3"], targets Float[Tensor, "3n"], weights
    Float[Tensor, "3n"] (ones)), the input of `solve_values`."""
    where = torch.cat([points, points + offset * normals, points - offset * normals])
    targets = torch.zeros(len(where), dtype=points.dtype, device=points.device)
    targets[len(points) : 2 * len(points)], targets[2 * len(points) :] = offset, -offset
    return where, targets, torch.ones_like(targets)


def cells_for_spacing(width: float, box: float, most: int, coarse: int) -> int:
    """Cells per side of a grid over [-box, box]^3 whose cells are at least `width` wide: a multiple of `coarse`,
    between 2 `coarse` and `most`. Cells finer than the points resolve would trace their noise."""
    return max(2 * coarse, min(most, int(2 * box / width) // coarse * coarse))


@torch.no_grad()
def voxel_start(points: Tensor, normals: Tensor, box: float, resolution: int = 256, band: int = 2, coarse: int = 8,
                prior_weight: float = 0.1, iterations: int = 10, winding_points: int = 5000, seed: int = 0,
                max_points: int = 1_000_000, spacings_per_cell: float | None = None, smoothness: float = 1.0,
                held_out: Tensor | None = None, refinements: int = 3, refinement_iterations: int = 5) -> VoxelSDF:
    """The start of a fit to Float[Tensor, "n 3"] unit-frame `points` with unit outward `normals` (see the
    module docstring): a VoxelSDF with every point of its (resolution + 1)^3 grid over [-box, box]^3 observed, on
    the points' device (a GPU's nearest-neighbour queries beyond `geometry.GPU_BRUTE_FORCE_PAIRS` run on the CPU).
    `resolution` must be a multiple of `coarse`; `prior_weight`, `iterations` and `refinement_iterations` are
    `solve_values`'. A cloud of more than `max_points` is read through a random subset of that many (`seed`): a
    million points sample a 256-cell grid several times over, and the solve's memory grows with the points. With
    `spacings_per_cell`, `resolution` is the most: cells are at least that many point spacings wide
    (`cells_for_spacing`). `smoothness` weighs the membrane term (`solve_values`) over the values within `coarse`
    cells of a point; 0: only the values the equations read are solved for, each held to its start. With
    Float[Tensor, "h 3"] `held_out` points (unit frame, kept out of the equations), up to `refinements` passes
    refine the solve (`solve_values`) while the mean |f| there falls, if it starts below `REFINE_BELOW` voxels: on a
    clean cloud they take back the membrane's bias (the bunny's 100k points: 1.20e-4 -> 5.3e-5 exact Chamfer-L1 in
    three); where the held-out points lie farther from the start's surface (noise, scans out of register, sparse
    points) that bias is not what limits it, and the passes would follow the noise. On such a clean cloud the values
    then go back toward their start by at most `KEEP_START` voxels, where the held-out points come closer (the
    bunny's: 5.3e-5 -> 4.1e-5)."""
    if not (resolution >= 2 * coarse >= 2 and resolution % coarse == 0 and band >= 1):
        raise ConfigError(f"voxel_start needs band >= 1 and a resolution that is a multiple of coarse, at least twice "
                          f"it; got resolution={resolution}, coarse={coarse}, band={band}")
    if normals is None or normals.shape != points.shape or len(points) < 2:
        raise InputError(f"voxel_start needs at least 2 points with one normal each, got points "
                         f"{tuple(points.shape)} and normals {None if normals is None else tuple(normals.shape)}")
    points, normals = points.detach().float(), normals.detach().to(points.device).float()
    if len(points) > max_points:
        chosen = torch.randperm(len(points), generator=torch.Generator().manual_seed(seed))[:max_points].to(points.device)
        points, normals = points[chosen], normals[chosen]
    spacing = cloud_spacing(points)
    if spacings_per_cell is not None:
        resolution = cells_for_spacing(spacing * spacings_per_cell, box, resolution, coarse)
    voxel = 2 * box / resolution
    size = resolution // coarse + 1
    far = signed_distance(grid_points(size, -box, coarse * voxel).to(points.device), points, normals, spacing,
                          winding_points, seed)
    values = torch.nn.functional.interpolate(far.reshape(1, 1, size, size, size), size=(resolution + 1,) * 3,
                                             mode="trilinear", align_corners=True)[0, 0]
    near = tuple(band_points(points, -box, voxel, resolution, band).T)
    values[near] = plane_distance(-box + torch.stack(near, -1).float() * voxel, points, normals, 2 * voxel)
    model = VoxelSDF.from_grid(values, torch.ones_like(values, dtype=torch.bool), [-box] * 3, voxel,
                               outside=box).to(points.device)
    unknowns = None
    if smoothness > 0:  # the values within a coarse cell of a point (a whole grid's rows are its grid order)
        i, j, k = band_points(points, -box, voxel, resolution, coarse).T
        unknowns = (i * (resolution + 1) + j) * (resolution + 1) + k
    held_out_error = None
    if held_out is not None and len(held_out):
        held_out = held_out.detach().to(points.device).float()

        def held_out_error(field: VoxelSDF) -> float:
            return float(field(held_out).abs().mean())

    start = model.values.detach().clone() if held_out_error else None
    model = solve_values(model, *point_equations(points, normals, voxel), prior_weight, iterations,
                         smoothness=smoothness, unknowns=unknowns, refinements=refinements if held_out_error else 0,
                         refinement_iterations=refinement_iterations,
                         score=held_out_error, score_below=REFINE_BELOW * voxel)
    if start is not None and (solved_error := held_out_error(model)) < REFINE_BELOW * voxel:
        solved = model.values.detach().clone()  # no value changes its sign: the zero level's topology is the solve's
        back = (start - solved).clamp_(-KEEP_START * voxel, KEEP_START * voxel)
        model.values.add_(back.masked_fill_((start > 0) != (solved > 0), 0.0))
        if not held_out_error(model) < solved_error:
            model.values.copy_(solved)
    return model
