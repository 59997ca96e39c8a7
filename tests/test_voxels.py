"""The voxel SDF (neuralsurf.models.grid), the edge rays that refine it (neuralsurf.observations.edges) and the
room fit built on both (neuralsurf.evaluation.rooms), against analytic oracles: a linear field, which trilinear
interpolation reproduces exactly, a plane seen by cameras facing it, and a step in depth."""

from __future__ import annotations

import functools

import pytest
import torch

from neuralsurf.evaluation.rooms import fused_voxels, voxel_mesh
from neuralsurf.models.grid import VoxelSDF
from neuralsurf.models.spec import build_model, model_spec
from neuralsurf.observations.edges import EdgeRays, edge_ratios
from neuralsurf.structures import DepthFrames, Normalization
from neuralsurf.training import fit

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


def test_edge_ratios_mark_the_far_side_of_a_depth_step():
    depth = torch.full((1, 20, 20), 2.0)
    depth[0, 5:10, 5:10] = 1.0  # a near patch
    depth[0, 15, 15] = 0.0  # a missing reading
    ratio = edge_ratios(depth, jump=0.05, window=2)
    assert ratio[0, 4, 7] == 0.5 and ratio[0, 11, 7] == 0.5 and ratio[0, 7, 3] == 0.5  # beside the patch
    assert ratio[0, 7, 7] == 0 and ratio[0, 12, 7] == 0 and ratio[0, 15, 15] == 0 and ratio[0, 0, 0] == 0


def test_edge_samples_lie_on_the_far_rays_at_the_near_depth():
    frames = plane_frames()
    frames.depth[:, 20:30, 20:40] = 1.0
    normalization = Normalization(torch.tensor([0.0, 0.0, 1.5], dtype=torch.float64), 2.0)
    sampler = EdgeRays(frames, pixel_stride=1, spread=0.01).prepare(normalization, 0.55, torch.device("cpu"), 0)
    batch = sampler.sample(torch.Generator().manual_seed(0))
    z = normalization.to_world(batch.edge_points.double())[:, 2]
    assert ((z - 1.0).abs() <= 0.011).all()  # z-depth 1 +- spread along rays whose readings are 2


def test_a_fused_plane_is_meshed_on_the_plane_and_its_fit_keeps_it_there():
    frames = plane_frames()
    bounds = torch.tensor([[-1.0, -0.8, 1.6], [1.0, 0.8, 2.4]], dtype=torch.float64)
    normalization = Normalization.from_points(bounds)
    model = fused_voxels(frames, bounds, 0.04, 0.16, normalization)
    mesh = voxel_mesh(model, normalization)
    assert (mesh.vertices[:, 2] - PLANE_Z).abs().max() < 1e-4
    result = fit(model, EdgeRays(frames, pixel_stride=2, n_rays=256, n_edge=0), steps=20, normalization=normalization,
                 optimizer=functools.partial(torch.optim.Adam, lr=1e-4), encoding_lr=None, device="cpu",
                 progress=False, image_every=0)
    refitted = voxel_mesh(result.model, normalization)
    assert (refitted.vertices[:, 2] - PLANE_Z).abs().max() < 2e-3 and len(refitted.faces) >= 0.9 * len(mesh.faces)


SHIFT = Normalization(torch.tensor([0.0, 0.0, 1.5], dtype=torch.float64), 1.0)
"""The unit frame of the analytic grids: the world shifted by 1.5 along z, so the scenes lie in the unit box."""


def grid_of(sdf, lo, hi, voxel):
    """A VoxelSDF (unit frame: SHIFT) of the analytic world `sdf` (points [..., 3] -> [...]) sampled on the grid
    over the world box lo..hi, observed within 0.1 of its surface."""
    axes = [torch.arange(a, b + 1e-9, voxel) for a, b in zip(lo, hi)]
    points = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1)
    values = sdf(points)
    return VoxelSDF.from_grid(values, values.abs() < 0.1, [lo[0], lo[1], lo[2] - 1.5], voxel, 0.1)


def fitted(model, observation, steps, lr):
    return fit(model, observation, steps=steps, normalization=SHIFT, optimizer=functools.partial(torch.optim.Adam, lr=lr),
               encoding_lr=None, device="cpu", progress=False, image_every=0).model


@pytest.mark.filterwarnings("ignore:after 60 steps the field has one sign")  # the box is mostly free space
def test_the_fit_moves_a_misplaced_plane_onto_the_readings():
    model = grid_of(lambda p: PLANE_Z + 0.015 - p[..., 2], (-0.6, -0.5, 1.8), (0.6, 0.5, 2.2), 0.02)  # 1.5 cm behind
    frames = plane_frames()
    model = fitted(model, EdgeRays(frames, pixel_stride=2, n_rays=512, n_edge=0, weights={"surface": 1.0, "band": 1.0}),
                   60, 1e-3)
    z = voxel_mesh(model, SHIFT).vertices[:, 2]
    central = z[(z - PLANE_Z).abs() < 0.05]
    assert (central - PLANE_Z).abs().median() < 3e-3 and len(central) > 0.9 * len(z)


def test_the_edge_term_trims_a_fattened_silhouette():
    """One camera sees a card at depth 1 (pixels 20-39 across: x in [-0.2, 0.133] there) in front of a wall at
    depth 2; the field's card is 3 cm too wide. The rays beside the card's image pass through that margin."""
    frames = plane_frames(xs=(0.0,))
    frames.depth[:, 20:30, 20:40] = 1.0
    low, high = torch.tensor([-0.2 - 0.03, -1 / 15 - 0.03, 1.0]), torch.tensor([0.4 / 3 + 0.03, 0.1 + 0.03, 1.02])

    def card_and_wall(p):
        outside = torch.maximum(low - p, p - high)
        card = outside.clamp_min(0).norm(dim=-1) + outside.amax(-1).clamp_max(0)
        return torch.minimum(card, PLANE_Z - p[..., 2])

    model = grid_of(card_and_wall, (-0.5, -0.4, 0.8), (0.5, 0.4, 2.2), 0.01)
    before = voxel_mesh(model, SHIFT).vertices
    observation = EdgeRays(frames, pixel_stride=1, window=3, spread=0.03, n_edge=4096, weights={"edge": 1.0})
    after = voxel_mesh(fitted(model, observation, 60, 2e-3), SHIFT).vertices
    width = lambda v: float(v[v[:, 2] < 1.5, 0].max())  # the card's right edge
    assert width(before) > 0.4 / 3 + 0.025 and width(after) < 0.4 / 3 + 0.012
