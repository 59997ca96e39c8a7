"""The closed-form start of a point fit (observations.start), the model that refines it (models.RefinedSDF) and
the fit's path through both (train.py's default), against analytic SDFs: a sphere and a box sampled with exact normals."""

from __future__ import annotations

import warnings
from pathlib import Path

import pytest
import torch
import trimesh
from hydra import compose, initialize_config_dir

import neuralsurf as ns
from neuralsurf.errors import ConfigError, InputError
from neuralsurf.models import RefinedSDF, VoxelSDF
from neuralsurf.models.spec import build_checked, model_spec
from neuralsurf.observations import PointSamples
from neuralsurf.observations.start import band_points, cells_for_spacing, point_equations, voxel_start
from neuralsurf.scenes.analytic import Box, Sphere

BOX = 0.55
CONFIGS = Path(__file__).resolve().parents[1] / "configs"


def grid_values(model: VoxelSDF) -> tuple[torch.Tensor, torch.Tensor]:
    """(the grid's points Float[Tensor, "n 3"], the model's values there Float[Tensor, "n"])."""
    values, observed = model.dense()
    index = observed.nonzero()
    return model.origin + index.float() * model.voxel, values[observed]


@pytest.mark.parametrize("shape", [Sphere(radius=0.3), Box(half_extents=(0.3, 0.2, 0.25))], ids=["sphere", "box"])
def test_the_start_is_the_analytic_sdf_near_the_points_and_has_its_sign_everywhere(shape):
    cloud = shape.sample_surface(10_000, seed=0)
    model = voxel_start(cloud.points.float(), cloud.normals.float(), BOX, resolution=64, coarse=4)
    points, values = grid_values(model)
    exact = shape.sdf(points.double()).float()
    voxel = 2 * BOX / 64
    assert model.voxel == pytest.approx(voxel) and len(values) == 65**3  # every grid point holds a value
    error = (values - exact)[exact.abs() < voxel].abs()
    # within a voxel of the surface: the distance to a few hundredths of a voxel mostly (the membrane term pulls
    # a curved surface's values toward their neighbours' mean); off the box's edges and corners the tangent planes
    # fall short of the distance (there the zero level, below, is what counts)
    assert error.median() < 0.03 * voxel
    if isinstance(shape, Sphere):
        assert error.max() < 0.2 * voxel
    far = exact.abs() > 6 * voxel  # beyond the band of tangent planes (off the box's edges they may err)
    assert torch.equal(values[far] > 0, exact[far] > 0)  # inside and outside, far from the points too
    mesh = ns.extract_mesh(model, 64, [[-0.5] * 3, [0.5] * 3], progress=False)
    assert mesh.is_watertight
    off = shape.sdf(mesh.vertices.double()).abs()
    assert off.median() < 0.05 * voxel and off.max() < 1.5 * voxel
    smooth = torch.ones(len(off), dtype=torch.bool)
    if isinstance(shape, Box):  # marching cubes cuts the box's edges and corners (a voxel); off them as smooth
        smooth = ((mesh.vertices.double().abs() - torch.tensor(shape.half_extents)).abs() < 2 * voxel).sum(-1) < 2
    assert off[smooth].max() < 0.3 * voxel


def test_held_out_points_refine_a_clean_start_toward_the_surface():
    """The membrane pulls a curved surface's values toward their neighbours' mean (the sphere's start lies 0.03
    voxel off it); with held-out points the solve is refined while their |f| falls, and the values it moved by less
    than a tenth of a voxel go back to their plane distances: the zero level comes closer to the analytic sphere
    (0.028 -> 0.010 voxel) and to the box (0.027 -> 0.014 voxel, whose flat faces' planes are exact), one piece
    with no wrong sign either way."""
    for shape in (Sphere(radius=0.3), Box(half_extents=(0.3, 0.2, 0.25))):
        cloud = shape.sample_surface(20_000, seed=0)
        points, normals = cloud.points.float(), cloud.normals.float()
        held_out = shape.sample_surface(1000, seed=1).points.float()
        off = []
        for extra in ({}, {"held_out": held_out}):
            model = voxel_start(points, normals, BOX, resolution=64, coarse=4, **extra)
            mesh = ns.extract_mesh(model, 64, [[-0.5] * 3, [0.5] * 3], progress=False)
            off.append(float(shape.sdf(mesh.vertices.double()).abs().mean()) / model.voxel)
            assert pieces_and_wrong_signs(model, shape) == (1, 0)
        assert off[1] < 0.6 * off[0]


def pieces_and_wrong_signs(model: VoxelSDF, shape) -> tuple[int, int]:
    """(connected pieces of the start's zero level, grid points more than two voxels from the surface on its wrong
    side)."""
    mesh = ns.extract_mesh(model, 64, [[-0.5] * 3, [0.5] * 3], progress=False)
    faces = trimesh.Trimesh(mesh.vertices.numpy(), mesh.faces.numpy(), process=False)
    points, values = grid_values(model)
    exact = shape.sdf(points.double()).float()
    far = exact.abs() > 2 * model.voxel
    return len(faces.split(only_watertight=False)), int(((values > 0) != (exact > 0))[far].sum())


UNSMOOTHED = {"smoothness": 0.0, "prior_weight": 1.0}  # each value held to its start, no membrane term


@pytest.mark.slow
def test_overlapping_out_of_register_scans_leave_the_smoothed_start_in_one_piece():
    """A second scan of the sphere's top, two voxels out along z (as real scans overlap slightly out of register):
    between the two sheets the nearest tangent plane changes side, and held to those values the start breaks into
    bubbles; the membrane term keeps one closed surface with the right sign everywhere."""
    sphere = Sphere(radius=0.3)
    cloud = sphere.sample_surface(20_000, seed=0)
    voxel = 2 * BOX / 64
    top = cloud.points[:, 2] > 0.15
    points = torch.cat([cloud.points, cloud.points[top] + torch.tensor([0.0, 0.0, 2 * voxel])]).float()
    normals = torch.cat([cloud.normals, cloud.normals[top]]).float()
    unsmoothed = voxel_start(points, normals, BOX, resolution=64, coarse=4, **UNSMOOTHED)
    assert pieces_and_wrong_signs(unsmoothed, sphere)[0] > 1  # the bubbles this guards against
    assert pieces_and_wrong_signs(voxel_start(points, normals, BOX, resolution=64, coarse=4), sphere) == (1, 0)
    kept = torch.arange(len(points)) % 20 > 0  # what a fit holds out scores the refinements: one surface still
    assert pieces_and_wrong_signs(voxel_start(points[kept], normals[kept], BOX, resolution=64, coarse=4,
                                              held_out=points[~kept]), sphere) == (1, 0)


def test_a_patch_of_flipped_normals_does_not_flip_the_smoothed_starts_sign():
    """Normals pointing inwards on a cap of the sphere (radius 0.08, about 360 of 20,000 points): their planes and
    equations say inside where it is outside; held to them the start takes the wrong sign off the cap, smoothed it
    keeps one surface with the analytic sign everywhere more than two voxels from it."""
    sphere = Sphere(radius=0.3)
    cloud = sphere.sample_surface(20_000, seed=0)
    flipped = (cloud.points - torch.tensor([0.0, 0.0, 0.3])).norm(dim=-1) < 0.08
    normals = torch.where(flipped[:, None], -cloud.normals, cloud.normals).float()
    points = cloud.points.float()
    assert pieces_and_wrong_signs(voxel_start(points, normals, BOX, resolution=64, coarse=4, **UNSMOOTHED),
                                  sphere)[1] > 0
    assert pieces_and_wrong_signs(voxel_start(points, normals, BOX, resolution=64, coarse=4), sphere) == (1, 0)
    kept = torch.arange(len(points)) % 20 > 0
    assert pieces_and_wrong_signs(voxel_start(points[kept], normals[kept], BOX, resolution=64, coarse=4,
                                              held_out=points[~kept]), sphere) == (1, 0)


def test_band_points_are_the_corners_of_the_cells_near_the_points():
    points = torch.tensor([[0.05, 0.05, 0.05]])  # in cell (5, 5, 5) of a 0.01 grid from 0
    near = band_points(points, 0.0, 0.01, 10, band=1)
    assert len(near) == 4**3  # cells 4..6 on each axis: their corners 4..7
    assert near.min() == 4 and near.max() == 7


def test_point_equations_ask_zero_on_the_points_and_the_offset_along_the_normals():
    points, normals = torch.zeros(2, 3), torch.tensor([[1.0, 0, 0], [0, 0, -1.0]])
    where, targets, weights = point_equations(points, normals, 0.1)
    assert torch.allclose(where[2:4], 0.1 * normals) and torch.allclose(where[4:], -0.1 * normals)
    assert targets.tolist() == pytest.approx([0, 0, 0.1, 0.1, -0.1, -0.1]) and torch.equal(weights, torch.ones(6))


def test_a_cloud_saved_twice_starts_as_one_copy():
    cloud = Sphere(radius=0.3).sample_surface(5000, seed=0)
    points, normals = cloud.points.float(), cloud.normals.float()
    once = voxel_start(points, normals, BOX, resolution=64, spacings_per_cell=1.0)
    twice = voxel_start(torch.cat([points, points]), torch.cat([normals, normals]), BOX, resolution=64,
                        spacings_per_cell=1.0)
    assert twice.shape == once.shape
    x = Sphere(radius=0.3).sample_surface(1000, seed=1).points.float()
    assert twice(x).abs().mean() < 0.1 * once.voxel


def test_the_start_needs_normals_and_a_resolution_its_coarse_grid_divides():
    cloud = Sphere(radius=0.3).sample_surface(100, seed=0)
    with pytest.raises(InputError, match="one normal each"):
        voxel_start(cloud.points.float(), None, BOX)
    with pytest.raises(ConfigError, match="multiple of coarse"):
        voxel_start(cloud.points.float(), cloud.normals.float(), BOX, resolution=60, coarse=8)


def small_refined(**options) -> RefinedSDF:
    encoding = ns.models.HashGrid(levels=2, log2_table_size=10, base_resolution=4, max_resolution=8)
    return RefinedSDF(width=16, depth=1, encoding=encoding, start_resolution=32, **options)


def test_refined_model_starts_at_its_start_and_its_checkpoint_spec_rebuilds_it():
    cloud = Sphere(radius=0.3).sample_surface(5000, seed=0)
    start = voxel_start(cloud.points.float(), cloud.normals.float(), BOX, resolution=32)
    model = small_refined()
    x = torch.rand(500, 3) - 0.5
    assert not torch.allclose(model(x), start(x))  # the MLP alone: a sphere of geometric initialisation
    model.set_start(start)
    assert torch.equal(model(x), start(x))  # the output layer zeroed: the start until trained
    assert not start.values.requires_grad
    with torch.no_grad():
        model.layers[-1].bias.fill_(0.01)
    state = model.state_dict()  # a whole grid: its values in grid order, no row index
    assert "start.values" in state and "start.rows" not in state
    rebuilt = build_checked(model_spec(model), state)  # as load_field does: a skeleton on the meta device first
    assert torch.equal(rebuilt.start.values, start.values) and torch.equal(rebuilt.start.rows, start.rows)
    assert torch.allclose(rebuilt(x), start(x) + 0.01 * start.voxel)


def test_a_partial_grid_keeps_its_row_index_and_a_whole_one_its_grid_order():
    values = torch.randn(9, 9, 9).cumsum(0)
    partial = VoxelSDF.from_grid(values, values < 0, [-0.5] * 3, 0.1)
    assert "rows" in partial.state_dict()
    linear = torch.randperm(9**3)
    whole = VoxelSDF.from_observed([9, 9, 9], linear, values.reshape(-1)[linear], [-0.5] * 3, 0.1, 1.0)
    assert torch.equal(whole.dense()[0], values)


def test_the_default_point_fit_refines_a_start_stops_on_held_out_points_and_extracts_sparsely():
    for data in ("sphere", "bunny", "file"):
        with initialize_config_dir(config_dir=str(CONFIGS), version_base="1.3"):
            default = compose(config_name="train", overrides=[f"data={data}"])
            method = compose(config_name="evaluate", overrides=["methods=[neural_sdf_fast]"]).method.neural_sdf_fast
        for cfg in (default, method):
            assert cfg.model._target_ == "neuralsurf.models.RefinedSDF" and cfg.model.start_resolution == 256
            points = cfg.observation.points if "observation" in cfg else cfg.observations.points
            assert points.held_out > 0 and cfg.trainer.patience > 0 and cfg.extract.sparse


@pytest.mark.slow
def test_a_point_fit_refines_the_start_and_stops_on_held_out_points():
    sphere = Sphere(radius=0.3)
    cloud = sphere.sample_surface(5000, seed=0)
    observation = PointSamples(cloud, n_near=20_000, n_free=5000, batch_size=512, held_out=0.05)
    result = ns.fit(small_refined(), observation, steps=400, patience=1, validate_every=5, device="cpu",
                    progress=False, image_every=0)
    assert isinstance(result.model.start, VoxelSDF) and result.model.start.shape == [33, 33, 33]
    assert result.steps < 400  # stopped by the held-out points
    x = sphere.sample_surface(2000, seed=3).points.float()
    assert result.field(x).abs().mean() < 0.5 * 1.1 / 32  # half a start voxel (world = unit frame here)
    with pytest.raises(ConfigError, match="patience"):
        ns.fit(small_refined(), observation, steps=5, patience=-1, device="cpu", progress=False)


def test_a_cloud_far_from_the_origin_is_fitted_and_meshed_on_top_of_itself():
    """Georeferenced coordinates (float32 rounds them by up to 0.25): the fit reads them about their own box, and
    its mesh comes back in float64 on the sphere."""
    far = torch.tensor([412_345.0, 5_012_345.0, 100.0], dtype=torch.float64)
    sphere = Sphere(center=tuple(far.tolist()), radius=0.3)
    observation = PointSamples(sphere.sample_surface(5000, seed=0), n_near=20_000, n_free=5000, batch_size=512)
    result = ns.fit(small_refined(), observation, steps=20, device="cpu", progress=False, image_every=0)
    mesh = ns.extract_mesh(result.field, 64, sparse=True, progress=False)
    assert mesh.vertices.dtype == torch.float64 and mesh.is_watertight
    assert sphere.sdf(mesh.vertices).abs().mean() < 0.5 * 0.6 * 1.1 / 32  # half a start voxel of its 0.6 box


def test_a_fit_stopped_on_held_out_points_stays_stopped_when_started_again(tmp_path):
    sphere = Sphere(radius=0.3)
    observation = PointSamples(sphere.sample_surface(2000, seed=0), n_near=4000, n_free=1000, batch_size=256,
                               held_out=0.05)
    options = {"steps": 300, "patience": 1, "validate_every": 5, "device": "cpu", "progress": False,
               "image_every": 0, "run_dir": tmp_path}
    first = ns.fit(small_refined(), observation, **options)
    assert first.steps < 300  # stopped by the held-out points
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no "nothing to train" either: the stop, not the step count, ends it
        again = ns.fit(small_refined(), observation, **options)
    assert again.steps == first.steps
    x = sphere.sample_surface(500, seed=1).points.float()
    assert torch.equal(first.field(x), again.field(x))


def test_held_out_share_is_checked_and_leaves_the_pools():
    cloud = Sphere(radius=0.3).sample_surface(1000, seed=0)
    with pytest.raises(ConfigError, match="held_out"):
        PointSamples(cloud, held_out=0.7)
    normalization = ns.Normalization.from_points(cloud.points)
    sampler = PointSamples(cloud, n_near=100, n_free=100, held_out=0.1).prepare(normalization, BOX, "cpu", 0)
    assert len(sampler.held_out) == 100 and len(sampler.samples.surface_points) == 900
    kept = {tuple(p) for p in sampler.samples.surface_points.tolist()}
    assert not kept & {tuple(p) for p in sampler.held_out.tolist()}
    sphere = Sphere(radius=0.3)
    exact = lambda x: sphere.sdf(normalization.to_world(x.double())) / normalization.scale  # unit frame
    assert sampler.held_out_error(exact) < 1e-6
    assert sampler.held_out_error(lambda x: exact(x) + 0.01) == pytest.approx(0.01, rel=1e-4)


def test_a_sparse_cloud_gets_a_start_of_cells_as_wide_as_its_points_spacing():
    assert cells_for_spacing(0.02, 0.55, 256, 8) == 48  # 55 cells of 0.02, down to a multiple of 8
    assert cells_for_spacing(0.001, 0.55, 256, 8) == 256 and cells_for_spacing(1.0, 0.55, 256, 8) == 16
    cloud = Sphere(radius=0.3).sample_surface(2000, seed=0)
    normalization = ns.Normalization.from_points(cloud.points)
    sampler = PointSamples(cloud, n_near=100, n_free=100).prepare(normalization, BOX, "cpu", 0)
    spacing = ns.geometry.cloud_spacing(sampler.samples.surface_points)
    start = sampler.start_field(256, BOX)
    assert start.shape[0] - 1 == cells_for_spacing(spacing, BOX, 256, 8) < 256
