"""The voxel SDF (neuralsurf.models.grid) and the room fit built on it (neuralsurf.rooms), against
oracles: a linear field, which trilinear interpolation reproduces exactly, a dense least-squares solve of the same
equations (with and without the grid's membrane term), and a plane seen by cameras facing it."""

from __future__ import annotations

import pytest
import torch

from neuralsurf.errors import ConfigError
from neuralsurf.models.grid import VoxelSDF, grid_adjacency, solve_values
from neuralsurf.models.spec import build_model, model_spec
from neuralsurf.rooms import fused_voxels, ray_equations, voxel_mesh
from neuralsurf.structures import DepthFrames, Normalization

WIDTH, HEIGHT, F, PLANE_Z = 64, 48, 60.0, 2.0


def plane_frames(xs=(-0.2, 0.0, 0.2)) -> DepthFrames:
    """Cameras at (x, 0, 0) looking along +z at the plane z = 2: depth 2 everywhere."""
    K = torch.tensor([[F, 0, (WIDTH - 1) / 2], [0, F, (HEIGHT - 1) / 2], [0, 0, 1]]).expand(len(xs), 3, 3).clone()
    pose = torch.eye(4).repeat(len(xs), 1, 1)
    pose[:, 0, 3] = torch.tensor(xs)
    return DepthFrames(torch.full((len(xs), HEIGHT, WIDTH), PLANE_Z), K, pose)


def linear_grid(shape=(6, 5, 4), voxel=0.1, origin=(-0.3, -0.2, -0.1)):
    """Values of the linear field 0.3 x - 0.5 y + 0.8 z + 0.05 at the grid points."""
    axes = [torch.arange(n) * voxel + o for n, o in zip(shape, origin)]
    x, y, z = torch.meshgrid(*axes, indexing="ij")
    return 0.3 * x - 0.5 * y + 0.8 * z + 0.05


def linear(points):
    return 0.3 * points[..., 0] - 0.5 * points[..., 1] + 0.8 * points[..., 2] + 0.05


def test_trilinear_interpolation_reproduces_a_linear_field_and_its_gradient():
    values = linear_grid()
    model = VoxelSDF.from_grid(values, torch.ones_like(values, dtype=torch.bool), (-0.3, -0.2, -0.1), 0.1)
    points = (torch.rand(200, 3, generator=torch.Generator().manual_seed(0)) * torch.tensor([0.5, 0.4, 0.3])
              + torch.tensor([-0.3, -0.2, -0.1])).requires_grad_(True)
    f = model(points)
    assert torch.allclose(f, linear(points), atol=1e-5)
    (gradient,) = torch.autograd.grad(f.sum(), points)
    assert torch.allclose(gradient, torch.tensor([0.3, -0.5, 0.8]).expand_as(gradient), atol=1e-4)


def test_a_whole_grid_reads_the_same_without_gradients_as_with_them():
    generator = torch.Generator().manual_seed(1)
    values = torch.randn(6, 5, 4, generator=generator)
    model = VoxelSDF.from_grid(values, torch.ones_like(values, dtype=torch.bool), (-0.3, -0.2, -0.1), 0.1, 2.0)
    points = torch.rand(500, 3, generator=generator) * 0.8 - 0.4  # some outside the grid: they read `outside`
    points[:3] = torch.tensor([[-0.3, -0.2, -0.1], [0.2, 0.2, 0.2], [0.1999, 0.1999, 0.1999]])  # corners
    with torch.no_grad():
        sampled = model(points)
    gathered = model(points.clone().requires_grad_(True)).detach()
    assert torch.allclose(sampled, gathered, atol=1e-5) and (sampled == 2.0).sum() > 50
    assert sampled[0] == values[0, 0, 0] and sampled[1] == 2.0


def test_unobserved_corners_are_left_out_and_unobserved_cells_read_outside():
    values = linear_grid()
    observed = torch.zeros_like(values, dtype=torch.bool)
    observed[0, 0, 0] = True
    model = VoxelSDF.from_grid(values, observed, (-0.3, -0.2, -0.1), 0.1, outside=0.7)
    inside_first_cell = torch.tensor([[-0.27, -0.16, -0.05]])
    assert torch.allclose(model(inside_first_cell), values[0, 0, 0].reshape(1))  # its one observed corner
    assert model(torch.tensor([[0.15, 0.15, 0.15]])).item() == pytest.approx(0.7)  # no observed corner
    assert model(torch.tensor([[5.0, 0.0, 0.0]])).item() == pytest.approx(0.7)  # outside the grid
    dense, seen = model.dense()
    assert torch.equal(seen, observed) and dense[0, 0, 0] == values[0, 0, 0] and torch.allclose(dense[~seen], torch.tensor(0.7))


def test_a_voxel_sdf_rebuilds_from_its_spec_and_state():
    values = linear_grid()
    model = VoxelSDF.from_grid(values, values > 0, (-0.3, -0.2, -0.1), 0.1)
    rebuilt = build_model(model_spec(model))
    rebuilt.load_state_dict(model.state_dict())
    points = torch.rand(50, 3) * 0.3 - 0.2
    assert torch.equal(rebuilt(points), model(points))


def test_the_solve_is_the_least_squares_solution_of_its_equations():
    """Conjugate gradients run to convergence give the dense normal equations' solution, and the field is linear in
    its values: model(points) is A v for the A the solve builds."""
    generator = torch.Generator().manual_seed(0)
    values = linear_grid()
    observed = torch.rand(values.shape, generator=generator) < 0.8
    model = VoxelSDF.from_grid(values, observed, (-0.3, -0.2, -0.1), 0.1)
    points = torch.rand(300, 3, generator=generator) * torch.tensor([0.5, 0.4, 0.3]) + torch.tensor([-0.3, -0.2, -0.1])
    targets, weights = torch.randn(300, generator=generator) * 0.05, torch.rand(300, generator=generator) + 0.5
    rows, w = model.corners(points)
    A = torch.zeros(300, len(model.values)).scatter_add_(1, rows, w).double()
    start = model.values[:, 0].detach().double()
    assert torch.allclose(model(points).double(), A @ start, atol=1e-6)
    diagonal = (A * A * weights.double()[:, None]).sum(0)
    lam = 2.0 * diagonal[diagonal > 0].mean()
    W = torch.diag(weights.double())
    expected = torch.linalg.solve(A.T @ W @ A + lam * torch.eye(len(start), dtype=torch.float64),
                                  A.T @ W @ targets.double() + lam * start)
    solved = solve_values(model, points, targets, weights, prior_weight=2.0, iterations=200).values[:, 0]
    assert torch.allclose(solved.double(), expected, atol=1e-5)
    with pytest.raises(ConfigError, match="prior_weight > 0"):
        solve_values(model, points, targets, weights, prior_weight=0.0)


def membrane_matrix(model: VoxelSDF) -> torch.Tensor:
    """The dense graph Laplacian of the observed grid points' axis edges, rows and columns in `values` order."""
    L = torch.zeros(len(model.values), len(model.values), dtype=torch.float64)
    rows = model.rows
    for axis in range(3):
        here, there = rows.narrow(axis, 0, rows.shape[axis] - 1), rows.narrow(axis, 1, rows.shape[axis] - 1)
        both = (here >= 0) & (there >= 0)
        i, j = here[both].long(), there[both].long()
        L.index_put_((i, i), torch.ones(len(i), dtype=torch.float64), accumulate=True)
        L.index_put_((j, j), torch.ones(len(j), dtype=torch.float64), accumulate=True)
        L.index_put_((i, j), -torch.ones(len(i), dtype=torch.float64), accumulate=True)
        L.index_put_((j, i), -torch.ones(len(i), dtype=torch.float64), accumulate=True)
    return L


def test_the_smoothed_solve_is_the_least_squares_solution_with_the_membrane_term():
    """With smoothness and every value an unknown, conjugate gradients reach the dense solution of
    (A^T W A + lam + mu L) v = A^T W t + lam v0, L the Laplacian of the grid's edges between observed points; with
    only some unknowns, the others are held at their start (the same system with those rows fixed)."""
    generator = torch.Generator().manual_seed(1)
    values = linear_grid() + 0.02 * torch.randn(linear_grid().shape, generator=generator)
    observed = torch.ones(values.shape, dtype=torch.bool)
    points = torch.rand(200, 3, generator=generator) * torch.tensor([0.5, 0.4, 0.3]) + torch.tensor([-0.3, -0.2, -0.1])
    targets, weights = torch.randn(200, generator=generator) * 0.05, torch.rand(200, generator=generator) + 0.5
    model = VoxelSDF.from_grid(values, observed, (-0.3, -0.2, -0.1), 0.1)
    rows, w = model.corners(points)
    A = torch.zeros(200, len(model.values)).scatter_add_(1, rows, w).double()
    start = model.values[:, 0].detach().double()
    W = torch.diag(weights.double())
    diagonal = (A * A * weights.double()[:, None]).sum(0)
    lam, mu = 0.1 * diagonal[diagonal > 0].mean(), 1.0 * diagonal[diagonal > 0].mean()
    system = A.T @ W @ A + lam * torch.eye(len(start), dtype=torch.float64) + mu * membrane_matrix(model)
    right = A.T @ W @ targets.double() + lam * start
    every = torch.arange(len(model.values))
    solved = solve_values(model, points, targets, weights, prior_weight=0.1, iterations=300, smoothness=1.0,
                          unknowns=every).values[:, 0].detach().double()
    exact = torch.linalg.solve(system, right)
    assert torch.allclose(solved, exact, atol=1e-5)
    # a refinement pass: the same system solved for a correction from the equations' residual (iterated Tikhonov)
    refined = exact + torch.linalg.solve(system, A.T @ W @ (targets.double() - A @ exact))
    model = VoxelSDF.from_grid(values, observed, (-0.3, -0.2, -0.1), 0.1)
    solved = solve_values(model, points, targets, weights, prior_weight=0.1, iterations=300, smoothness=1.0,
                          unknowns=every, refinements=1).values[:, 0].detach().double()
    assert torch.allclose(solved, refined, atol=1e-5)
    def misfit(v: torch.Tensor) -> float:  # the equations' weighted squared residual
        return float(weights.double() @ (A @ v - targets.double()) ** 2)

    assert misfit(refined) < misfit(exact)  # a pass takes back some of what the prior and the membrane held
    scores = iter([1.0, 0.9, 0.97])  # kept while the score falls by REFINEMENT_GAIN: one pass of three
    model = VoxelSDF.from_grid(values, observed, (-0.3, -0.2, -0.1), 0.1)
    solved = solve_values(model, points, targets, weights, prior_weight=0.1, iterations=300, smoothness=1.0,
                          unknowns=every, refinements=3, score=lambda field: next(scores)).values[:, 0].detach()
    assert torch.allclose(solved.double(), refined, atol=1e-5) and next(scores, None) is None
    held = every[::3]  # no equation reads a value far from the points: make some rows held by leaving them out
    free = torch.ones(len(start), dtype=torch.bool)
    free[held] = False
    free[rows.unique()] = True  # the values the equations read are always unknowns
    model = VoxelSDF.from_grid(values, observed, (-0.3, -0.2, -0.1), 0.1)
    solved = solve_values(model, points, targets, weights, prior_weight=0.1, iterations=300, smoothness=1.0,
                          unknowns=every[free]).values[:, 0].detach().double()
    expected = start.clone()
    expected[free] = torch.linalg.solve(system[free][:, free], right[free] - system[free][:, ~free] @ start[~free])
    assert torch.allclose(solved, expected, atol=1e-5)
    with pytest.raises(ConfigError, match="smoothness >= 0"):
        solve_values(model, points, targets, weights, smoothness=-1.0)
    with pytest.raises(ConfigError, match="refinements >= 0"):
        solve_values(model, points, targets, weights, refinements=-1)
    sparse = VoxelSDF.from_grid(values, torch.rand(values.shape, generator=generator) < 0.8, (-0.3, -0.2, -0.1), 0.1)
    with pytest.raises(ConfigError, match="whole grid"):
        solve_values(sparse, points, targets, weights, smoothness=1.0)


def test_a_smoothed_solve_away_from_the_grid_s_faces_is_the_same_least_squares_solution():
    """Unknowns that all lie inside the grid (six grid neighbours each) against the dense system with the
    other rows held at their start."""
    generator = torch.Generator().manual_seed(2)
    values = torch.randn(7, 7, 7, generator=generator) * 0.1
    model = VoxelSDF.from_grid(values, torch.ones(values.shape, dtype=torch.bool), (0.0, 0.0, 0.0), 0.1)
    points = 0.2 + 0.2 * torch.rand(100, 3, generator=generator)  # cells 2 and 3: corners 2 to 4 on each axis
    targets, weights = torch.randn(100, generator=generator) * 0.05, torch.rand(100, generator=generator) + 0.5
    rows, w = model.corners(points)
    A = torch.zeros(100, len(model.values)).scatter_add_(1, rows, w).double()
    start, W = model.values[:, 0].detach().double(), torch.diag(weights.double())
    diagonal = (A * A * weights.double()[:, None]).sum(0)
    lam, mu = 0.1 * diagonal[diagonal > 0].mean(), 1.0 * diagonal[diagonal > 0].mean()
    system = A.T @ W @ A + lam * torch.eye(len(start), dtype=torch.float64) + mu * membrane_matrix(model)
    right = A.T @ W @ targets.double() + lam * start
    i, j, k = torch.meshgrid(*[torch.arange(1, 6)] * 3, indexing="ij")
    inner = ((i * 7 + j) * 7 + k).reshape(-1)  # every point off the faces
    free = torch.zeros(len(start), dtype=torch.bool)
    free[inner] = True
    solved = solve_values(model, points, targets, weights, prior_weight=0.1, iterations=300, smoothness=1.0,
                          unknowns=inner).values[:, 0].detach().double()
    expected = start.clone()
    expected[free] = torch.linalg.solve(system[free][:, free], right[free] - system[free][:, ~free] @ start[~free])
    assert torch.allclose(solved, expected, atol=1e-5)


def test_the_grid_adjacency_links_exactly_the_axis_neighbours():
    generator = torch.Generator().manual_seed(3)
    linear = torch.randperm(6 * 5 * 7, generator=generator)[:120].sort().values  # distinct, in grid order
    coordinates = torch.stack([linear // 35, linear // 7 % 5, linear % 7], -1)
    expected = ((coordinates[:, None] - coordinates[None]).abs().sum(-1) == 1).float()
    adjacency = grid_adjacency(coordinates)
    assert torch.equal(adjacency.to_dense(), expected)
    values = torch.randn(len(linear), generator=generator)
    assert torch.allclose(adjacency @ values, expected @ values, atol=1e-6)


def test_ray_equations_ask_zero_at_the_hits_and_the_normal_distance_around_them():
    frames = plane_frames(xs=(0.0,))
    normalization = Normalization(torch.tensor([0.0, 0.0, 1.5], dtype=torch.float64), 2.0)
    points, targets, weights = ray_equations(frames, normalization, voxel=0.01, pixel_stride=4, n_band=2)
    assert len(points) == 3 * (HEIGHT // 4) * (WIDTH // 4)
    assert weights.mean() == pytest.approx(1.0) and (weights.reshape(-1, 3) == weights[::3, None]).all()  # per ray
    z = normalization.to_world(points.double())[:, 2]
    distance = (PLANE_Z - z) / normalization.scale  # the plane's signed distance, unit frame, + in front
    assert torch.allclose(targets.double(), distance, atol=1e-6)
    assert (targets == 0).sum() == len(points) // 3 and targets.abs().max() > 0.004  # the band: 1 voxel at least


def test_the_solve_moves_a_misplaced_plane_onto_the_readings_and_keeps_a_fused_one():
    frames = plane_frames()
    bounds = torch.tensor([[-1.0, -0.8, 1.6], [1.0, 0.8, 2.4]], dtype=torch.float64)
    normalization = Normalization.from_points(bounds)
    model = fused_voxels(frames, bounds, 0.04, 0.16, normalization)
    assert (voxel_mesh(model, normalization).vertices[:, 2] - PLANE_Z).abs().max() < 1e-4
    kept = voxel_mesh(solve_values(model, *ray_equations(frames, normalization, model.voxel, 2)), normalization)
    assert (kept.vertices[:, 2] - PLANE_Z).abs().max() < 1e-3

    behind = grid_of(lambda p: PLANE_Z + 0.015 - p[..., 2], (-0.6, -0.5, 1.8), (0.6, 0.5, 2.2), 0.02)  # 1.5 cm
    moved = solve_values(behind, *ray_equations(frames, SHIFT, behind.voxel, 1), prior_weight=0.01, iterations=50)
    z = voxel_mesh(moved, SHIFT).vertices[:, 2]
    central = z[(z - PLANE_Z).abs() < 0.05]
    assert (central - PLANE_Z).abs().median() < 2e-3 and len(central) > 0.9 * len(z)


SHIFT = Normalization(torch.tensor([0.0, 0.0, 1.5], dtype=torch.float64), 1.0)
"""The unit frame of the analytic grids: the world shifted by 1.5 along z, so the scenes lie in the unit box."""


def grid_of(sdf, lo, hi, voxel):
    """A VoxelSDF (unit frame: SHIFT) of the analytic world `sdf` (points [..., 3] -> [...]) sampled on the grid
    over the world box lo..hi, observed within 0.1 of its surface."""
    axes = [torch.arange(a, b + 1e-9, voxel) for a, b in zip(lo, hi)]
    points = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1)
    values = sdf(points)
    return VoxelSDF.from_grid(values, values.abs() < 0.1, [lo[0], lo[1], lo[2] - 1.5], voxel, 0.1)
