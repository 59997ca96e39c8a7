"""Completion that keeps what was seen (priors.refinement) and the per-class answer of the report
(evaluation.per_class): analytic priors and shapes as oracles."""

import numpy as np
import pytest
import torch
from torch import nn

from neuralsurf.cameras import backproject_depth, box_span
from neuralsurf.errors import ConfigError, InputError
from neuralsurf.evaluation.per_class import class_comparison, shape_class
from neuralsurf.evaluation.report import per_class_markdown
from neuralsurf.extract import extract_mesh
from neuralsurf.geometry import point_to_mesh_distance
from neuralsurf.priors import csg
from neuralsurf.priors.completion import EXTRACTION_BOUNDS, extract_unit
from neuralsurf.priors.refinement import (
    FitSamples,
    Refinement,
    field_scale,
    fit_residual,
    grid_lookup,
    refine_to_view,
    trilinear_weights,
    view_samples,
)
from neuralsurf.scenes.scanner import ONE_VIEW_IMAGE, one_view_camera, scan_depth
from neuralsurf.structures import DepthFrames

BOUNDS = torch.as_tensor(EXTRACTION_BOUNDS)


class Analytic(nn.Module):
    """An analytic SDF as a module (a prior's field has parameters: they say where it runs)."""

    def __init__(self, sdf):
        super().__init__()
        self.sdf = sdf
        self.anchor = nn.Parameter(torch.zeros(()), requires_grad=False)

    def forward(self, x):
        return self.sdf(x)


def rounded_box(x):
    return csg.box(x, (0.02, 0.0, 0.0), (0.3, 0.22, 0.18), 0.03)


def small_sphere(x):
    return csg.sphere(x, (0.0, 0.0, 0.0), 0.28)


@pytest.fixture(scope="module")
def seen_box():
    """A rounded box (the truth), one noisy view of it, and a sphere prior that disagrees with it."""
    truth = extract_mesh(Analytic(rounded_box), resolution=96, bounds=EXTRACTION_BOUNDS, progress=False)
    frames = scan_depth(truth, cam_to_world=one_view_camera(3, 1.6)[None], **ONE_VIEW_IMAGE, noise="gaussian",
                        sigma=0.001, seed=0)
    return truth, frames


def test_trilinear_weights_interpolate_a_linear_grid_exactly():
    n = 9
    axis = torch.linspace(-0.55, 0.55, n, dtype=torch.float64)
    z, y, x = torch.meshgrid(axis, axis, axis, indexing="ij")
    grid = 2 * x - 3 * y + 0.5 * z + 1  # nodes in z, y, x order
    points = torch.rand(200, 3, dtype=torch.float64) - 0.5
    nodes, weights = trilinear_weights(points, BOUNDS, n)
    values = (grid.reshape(-1)[nodes] * weights).sum(-1)
    expected = 2 * points[:, 0] - 3 * points[:, 1] + 0.5 * points[:, 2] + 1
    assert torch.allclose(values, expected, atol=1e-9)
    assert torch.allclose(weights.sum(-1), torch.ones(200, dtype=torch.float64))
    assert torch.allclose(grid_lookup(grid, points, BOUNDS), expected, atol=1e-9)
    beyond = torch.tensor([[0.9, 0.0, 0.0]], dtype=torch.float64)  # clamped to the box's face
    for face in (BOUNDS[1], BOUNDS[1].float(), BOUNDS[0].float()):  # on the far face in float32 too
        assert torch.allclose(grid_lookup(grid.float(), face[None], BOUNDS), (2 * face[0] - 3 * face[1] + 0.5 * face[2] + 1
                                                                              ).float()[None], atol=1e-5)
    assert torch.allclose(grid_lookup(grid, beyond, BOUNDS), grid_lookup(grid, beyond.clamp(-0.55, 0.55), BOUNDS))


def test_box_span_enters_and_leaves_the_box_where_the_slabs_say():
    origins = torch.tensor([[-2.0, 0.0, 0.0], [-2.0, 2.0, 0.0]], dtype=torch.float64)
    directions = torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]], dtype=torch.float64)
    entry, exit_ = box_span(origins, directions, BOUNDS)
    assert entry[0] == pytest.approx(2 - 0.55) and exit_[0] == pytest.approx(2 + 0.55)
    assert exit_[1] <= entry[1]  # the second ray passes above the box


def test_view_samples_lie_on_in_front_of_and_behind_the_seen_surface(seen_box):
    _, frames = seen_box
    settings = Refinement()
    samples = view_samples(frames, BOUNDS, settings)
    hits = backproject_depth(frames)[frames.depth > 0].double()
    assert torch.equal(samples.surface, hits)
    assert len(samples.behind) == len(hits)
    truth = rounded_box
    assert (truth(samples.behind) < 0).float().mean() > 0.95  # 5 mm behind a 1 mm-noise hit: inside
    assert (truth(samples.free) > 0).float().mean() > 0.99  # seen empty: outside
    inside_box = ((samples.free >= BOUNDS[0] - 1e-9) & (samples.free <= BOUNDS[1] + 1e-9)).all(-1)
    assert inside_box.all()


def test_a_refined_completion_holds_the_seen_surface_and_keeps_the_prior_elsewhere(seen_box):
    _, frames = seen_box
    prior = Analytic(small_sphere)
    refined = refine_to_view(prior, frames, BOUNDS)
    hits = backproject_depth(frames)[frames.depth > 0].double()
    before = small_sphere(hits).abs()  # the sphere's own distance to the hits
    mesh = extract_unit(refined, 128)
    after = point_to_mesh_distance(hits, mesh)
    assert before.mean() > 0.04  # the sphere misses the box's seen side by centimetres
    assert after.mean() < 0.002 and torch.quantile(after, 0.95) < 0.005  # the view's noise is 1 mm
    # far from the view (the side facing away from the camera) the completion is the prior's sphere
    camera = frames.cam_to_world[0, :3, 3].double()
    far = -0.28 * camera / camera.norm()
    assert abs(float(refined(far[None].float()))) < 0.01
    assert mesh.is_watertight


def test_a_field_in_other_units_is_refined_in_distances():
    """An occupancy network's field is a logit, not a distance: the residual is fitted to field / k, k the
    median gradient norm at the seen points, so the same settings move its surface as far."""
    points = torch.randn(500, 3, dtype=torch.float64)
    points = 0.28 * points / points.norm(dim=-1, keepdim=True)
    steep = Analytic(lambda x: 25 * small_sphere(x))
    assert field_scale(steep, points) == pytest.approx(25, rel=1e-4)
    samples = FitSamples(1.1 * points, points.new_zeros(0, 3), points.new_zeros(0, 3))  # a sphere 10 % larger
    settings = Refinement(resolution=24, steps=60, decay=0.0)
    for prior in (Analytic(small_sphere), steep):
        refined = fit_residual(prior, samples, BOUNDS, settings)
        assert refined(1.1 * points.float()).abs().mean() < 0.004


def test_refinement_settings_and_inputs_are_checked():
    with pytest.raises(ConfigError, match="resolution"):
        Refinement(resolution=1)
    with pytest.raises(ConfigError, match=">= 0"):
        Refinement(decay=-1.0)
    empty = DepthFrames(torch.zeros(1, 4, 4), torch.tensor([[4.0, 0, 2], [0, 4.0, 2], [0, 0, 1]]), torch.eye(4))
    with pytest.raises(InputError, match="no valid depth"):
        view_samples(empty, BOUNDS)


def _set_row(method, values):
    per_shape = [{"shape": name, "chamfer_l1_exact": chamfer, "fscore_1%": fscore}
                 for name, (chamfer, fscore) in values.items()]
    return {"method": method, "scene": "shapes_one_view", "status": "ok", "per_shape": per_shape}


def test_per_class_comparison_counts_the_shapes_each_method_wins_against_each_baseline():
    shapes = ["chair_test_0000", "chair_test_0001", "mug_test_0000"]
    rows = [_set_row("deepsdf", dict(zip(shapes, [(0.01, 0.6), (0.03, 0.5), (0.02, 0.7)]))),
            _set_row("tsdf", dict(zip(shapes, [(0.02, 0.5), (0.02, 0.5), (0.04, 0.6)]))),
            _set_row("poisson", dict(zip(shapes, [(0.05, 0.3), (0.06, 0.3), (0.01, 0.9)])))]
    entries = {(e["class"], e["method"]): e for e in class_comparison(rows)}
    assert set(entries) == {("chair", "deepsdf"), ("mug", "deepsdf"), ("all", "deepsdf")}
    chair = entries["chair", "deepsdf"]
    assert chair["shapes"] == 2 and chair["chamfer"] == pytest.approx(0.02)
    assert chair["tsdf_ratio"] == pytest.approx(1.0) and chair["tsdf_wins"] == 1
    assert chair["poisson_ratio"] == pytest.approx(0.055 / 0.02) and chair["poisson_wins"] == 2
    assert chair["best_ratio"] == pytest.approx(1.0)
    mug = entries["mug", "deepsdf"]
    assert mug["tsdf_wins"] == 1 and mug["poisson_wins"] == 0 and mug["best_ratio"] == pytest.approx(0.5)
    assert entries["all", "deepsdf"]["shapes"] == 3
    table = per_class_markdown(rows)
    assert "| shapes_one_view | chair | deepsdf | 2 | 0.02 | 0.550 | 1.00x (1/2) | 0.500 | 2.75x (2/2) | 0.300 |" in table
    assert shape_class("slat_chair_test_0012") == "slat_chair" and shape_class("bunny") == "bunny"
    assert per_class_markdown([{**rows[0], "per_shape": None}]) == ""


@pytest.mark.slow
def test_a_small_prior_trained_on_a_damaged_folder_completes_one_view_better_than_its_tsdf(tmp_path):
    """Item of record: a DeepSDF prior trained in seconds on a procedural folder of damaged mugs
    (holes, duplicated and inner sheets, reversed faces) completes each held-out mug from one depth
    view with a lower exact Chamfer-L1 than TSDF fusion of the same view, which sees only one side."""
    from functools import partial

    from neuralsurf.evaluation.methods import learned_prior, tsdf
    from neuralsurf.metrics import evaluate_mesh
    from neuralsurf.priors import CollectionSDF, deepsdf, shapes_one_view, train_prior
    from neuralsurf.priors.folders import FolderCollection
    from neuralsurf.priors.mesh_folders import write_procedural_folder

    write_procedural_folder(tmp_path / "mugs", ("mug",), n_train=8, n_test=2, resolution=40, seed=0)
    collection = FolderCollection(str(tmp_path / "mugs" / "damaged"), n_sdf=8000, n_occ=500, n_surface=2000,
                                  root=str(tmp_path / "cache"), workers=0)
    collection.build(progress=False)
    model = partial(deepsdf, latent_dim=16, width=64, depth=4, skip_layers=(2,))
    observations = [partial(CollectionSDF.from_collection, shapes_per_batch=8, samples_per_shape=512)]
    train_prior(collection, model, observations, trainer={"steps": 400, "progress": False, "image_every": 0,
                                                          "mesh_every": 0, "encoding_lr": None},
                run_dir=tmp_path / "prior", optimizer=partial(torch.optim.Adam, lr=5e-3))
    checkpoint = str(tmp_path / "prior" / "checkpoints" / "last.pt")
    scenes = shapes_one_view(collection)
    assert len(scenes.scenes) == 2
    for scene in scenes.scenes:
        prior_mesh = learned_prior(scene, checkpoint=checkpoint, latent_steps=100, resolution=64, refine={},
                                   device="cpu")
        tsdf_mesh = tsdf(scene, voxel_fraction=1 / 128, device="cpu")
        prior_chamfer = float(evaluate_mesh(prior_mesh, scene.ground_truth, n_samples=5000)["chamfer_l1_exact"])
        tsdf_chamfer = float(evaluate_mesh(tsdf_mesh, scene.ground_truth, n_samples=5000)["chamfer_l1_exact"])
        assert prior_chamfer < tsdf_chamfer, (scene.name, prior_chamfer, tsdf_chamfer)


def test_points_are_drawn_where_the_renders_camera_sees_them():
    from neuralsurf.evaluation.render import default_view, points_image, raycast
    from neuralsurf.structures import Mesh

    view = default_view(BOUNDS.numpy())
    image = points_image(view["center"][None], view, 64, 64)
    dark = (image[..., 0] < 255).nonzero()
    assert {int(dark[0].min()), int(dark[1].min())} <= {31, 32}  # the centre of the view is the centre pixel
    # a triangle's centroid is drawn where the raycast sees the triangle
    corner = view["center"] + np.array([0.2, 0.0, 0.0])
    triangle = Mesh(torch.tensor(np.stack([corner, corner + [0.06, 0, 0], corner + [0, 0.06, 0.06]])),
                    torch.tensor([[0, 1, 2]]))
    hit = np.argwhere(raycast(triangle, view, 64, 64)[0]).mean(0)
    drawn = np.argwhere(points_image(triangle.vertices.numpy().mean(0)[None], view, 64, 64)[..., 0] < 255).mean(0)
    assert np.abs(hit - drawn).max() < 2.5, (hit, drawn)
