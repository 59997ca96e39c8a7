"""Learned shape priors: DeepSDF auto-decoder and latent reconstruction, Occupancy Network, and
their observations over a shape collection."""

import dataclasses
import functools

import numpy as np
import pytest
import torch
from torch import Tensor, nn

from neuralsurf.errors import ConfigError, FileFormatError, InputError
from neuralsurf.geometry import noisy_cloud
from neuralsurf.io.npz import write_npz
from neuralsurf.losses import clamped_l1, eikonal_loss
from neuralsurf.models import (
    SDFMLP,
    AutoDecoder,
    CBNDecoder,
    ConditionalBatchNorm,
    LatentCodes,
    LatentConditioned,
    OccupancyNetwork,
    PointNetEncoder,
)
from neuralsurf.models.occupancy import local_pool, plane_cells, plane_means, sample_planes
from neuralsurf.models.spec import build_model, model_spec
from neuralsurf.priors import ShapeRecord, complete_cloud
from neuralsurf.priors.cache import CacheRecipe, SplitArrays, build_collection, cache_path, load_cache
from neuralsurf.priors.completion import reconstruct_latent
from neuralsurf.priors.observations import (
    CollectionOccupancy,
    CollectionSDF,
    LatentPrior,
    SDFSampleSet,
    draw_shape_sdf,
    view_clouds,
)
from neuralsurf.structures import Mesh, Normalization
from neuralsurf.training import default_optimizer, fit

RECORDS = [ShapeRecord("lamp", "train", 0), ShapeRecord("chair", "train", 0)]
RECIPE = CacheRecipe(n_sdf=20_000, n_occ=4000, n_surface=2000, mesh_resolution=48)


@pytest.fixture(scope="module")
def collection(tmp_path_factory):
    root = tmp_path_factory.mktemp("shapes")
    build_collection(root, RECORDS, RECIPE, progress=False)
    return root


def _label_iou(field_values: torch.Tensor, inside: torch.Tensor) -> float:
    pred = field_values < 0
    return float((pred & inside).sum() / (pred | inside).sum())


def _uniform_labels(root, record):
    arrays = load_cache(cache_path(root, record))
    return torch.from_numpy(arrays["occ_uniform_points"]), torch.from_numpy(arrays["occ_uniform_inside"])


@pytest.fixture(scope="module")
def auto_decoder(collection):
    """A small DeepSDF auto-decoder trained on two shapes (a lamp and a chair) through `fit`."""
    torch.manual_seed(0)
    decoder = SDFMLP(width=48, depth=4, skip_layers=(2,), latent_dim=8, init_radius=0.3)
    model = AutoDecoder(decoder, LatentCodes(len(RECORDS), 8))
    result = fit(model, CollectionSDF(collection, shapes_per_batch=2, samples_per_shape=1024), steps=250,
                 normalization=Normalization(), encoding_lr=None, progress=False, log_every=50,
                 optimizer=functools.partial(default_optimizer, lr=5e-3))
    return result


def test_latent_codes_start_as_deepsdf_says_and_reject_foreign_indices():
    torch.manual_seed(0)
    codes = LatentCodes(400, 64)
    assert codes.weight.std().item() == pytest.approx(0.01, rel=0.05)
    assert codes.weight.mean().abs().item() < 1e-3
    assert codes(torch.tensor([[1, 2], [3, 4]])).shape == (2, 2, 64)
    with pytest.raises(InputError, match="outside the training collection"):
        codes(torch.tensor([400]))
    with pytest.raises(ConfigError, match="latent_dim=8"):
        AutoDecoder(SDFMLP(width=32, depth=2, skip_layers=(), latent_dim=4), LatentCodes(2, 8))


def test_prior_models_rebuild_from_plain_specs():
    torch.manual_seed(0)
    decoder = SDFMLP(width=32, depth=3, skip_layers=(1,), latent_dim=4)
    for model in (AutoDecoder(decoder, LatentCodes(3, 4)), LatentConditioned.from_code(decoder, torch.ones(4)),
                  OccupancyNetwork(PointNetEncoder(16, 16), CBNDecoder(16, 32), threshold=0.2)):
        rebuilt = build_model(model_spec(model))
        rebuilt.load_state_dict(model.state_dict())
        x = torch.rand(50, 3) - 0.5
        model.eval(), rebuilt.eval()
        latent = torch.randn(16) if isinstance(model, OccupancyNetwork) else None
        assert torch.equal(model(x, latent), rebuilt(x, latent))



def test_feature_planes_are_read_in_the_cells_they_were_written_to():
    """Oracle: a naive loop over points and planes (cell means, local pooling) and the cell centres:
    bilinear reads of a plane at its own cell centres return the cell values."""
    torch.manual_seed(0)
    r, half = 4, 0.55
    points = torch.rand(2, 30, 3) * 1.2 - 0.6          # some outside the box: they use the border cells
    features = torch.randn(2, 30, 5)
    cells = plane_cells(points, r, half)
    naive = torch.zeros(2, 3, r * r, 5)
    for b in range(2):
        for k, (i, j) in enumerate([(0, 1), (0, 2), (1, 2)]):
            uv = ((points[b][:, [i, j]] / half).clamp(-1, 1) + 1) / 2 * r
            u, v = uv.long().clamp(0, r - 1).unbind(-1)
            for cell in range(r * r):
                members = (v * r + u) == cell
                if members.any():
                    naive[b, k, cell] = features[b][members].mean(0)
    means = plane_means(features, cells, r)
    assert torch.allclose(means, naive, atol=1e-6)
    pooled = torch.stack([sum(naive[b, k, cells[b, k]] for k in range(3)) for b in range(2)])
    assert torch.allclose(local_pool(features, cells, r), pooled, atol=1e-6)
    planes = torch.zeros(2, 3, 5, r, r)                                  # only the xy plane written
    planes[:, 0] = means[:, 0].transpose(1, 2).reshape(2, 5, r, r)
    centres = (torch.arange(r) + 0.5) / r * 2 * half - half            # cell centres along one axis
    y, x = torch.meshgrid(centres, centres, indexing="ij")               # row-major: v = y, u = x
    reads = sample_planes(planes, torch.stack([x.flatten(), y.flatten(), torch.zeros(r * r)], -1).expand(2, -1, -1),
                          half)
    assert torch.allclose(reads, means[:, 0], atol=1e-5)


def test_occupancy_network_with_feature_planes_is_permutation_invariant_and_rebuilds():
    torch.manual_seed(0)
    net = OccupancyNetwork(PointNetEncoder(8, 16, plane_dim=4, plane_resolution=8),
                           CBNDecoder(8, 16, blocks=2, plane_dim=4, plane_resolution=8)).eval()
    cloud = torch.rand(2, 200, 3) - 0.5
    code = net.encode(cloud)
    assert code.shape == (2, 8 + 3 * 4 * 8 * 8)
    assert torch.allclose(net.encode(cloud[:, torch.randperm(200)]), code, atol=1e-5)
    x = torch.rand(50, 3) - 0.5
    rebuilt = build_model(model_spec(net)).eval()
    rebuilt.load_state_dict(net.state_dict())
    assert torch.equal(rebuilt(x, code[0]), net(x, code[0]))
    # the planes matter: another cloud's planes under the same global code give another field
    swapped = torch.cat([code[0, :8], code[1, 8:]])
    assert not torch.allclose(net(x, swapped), net(x, code[0]), atol=1e-4)
    with pytest.raises(ConfigError, match="layout"):
        OccupancyNetwork(PointNetEncoder(8, 16, plane_dim=4, plane_resolution=8), CBNDecoder(8, 16))
    with pytest.raises(ConfigError, match="divisible"):
        PointNetEncoder(8, 16, plane_dim=4, plane_resolution=6)

def test_conditional_batch_norm_with_a_constant_code_is_batch_norm_with_those_affine_parameters():
    torch.manual_seed(0)
    cbn = ConditionalBatchNorm(c_dim=6, features=5)
    nn.init.normal_(cbn.gamma.weight), nn.init.normal_(cbn.beta.weight)
    nn.init.normal_(cbn.gamma.bias), nn.init.normal_(cbn.beta.bias)
    code = torch.randn(6)
    bn = nn.BatchNorm1d(5, affine=True)
    with torch.no_grad():
        bn.weight.copy_(cbn.gamma(code))
        bn.bias.copy_(cbn.beta(code))
    x = torch.randn(3, 40, 5)
    for _ in range(3):  # train mode: batch statistics, and the same running averages
        ours = cbn(x, code.expand(3, 6))
        reference = bn(x.reshape(-1, 5)).reshape(3, 40, 5)
        assert torch.allclose(ours, reference, atol=1e-5)
        x = 2 * x + 1
    assert torch.allclose(cbn.bn.running_mean, bn.running_mean) and torch.allclose(cbn.bn.running_var, bn.running_var)
    cbn.eval(), bn.eval()
    assert torch.allclose(cbn(x, code.expand(3, 6)), bn(x.reshape(-1, 5)).reshape(3, 40, 5), atol=1e-5)


def test_occupancy_network_is_permutation_invariant_and_its_field_is_minus_the_shifted_logit():
    torch.manual_seed(0)
    net = OccupancyNetwork(PointNetEncoder(16, 16), CBNDecoder(16, 32)).eval()
    cloud = torch.rand(2, 100, 3) - 0.5
    code = net.encode(cloud)
    assert code.shape == (2, 16)
    assert torch.allclose(net.encode(cloud[:, torch.randperm(100)]), code, atol=1e-6)
    x = torch.rand(7, 5, 3) - 0.5
    logits = net.logits(x.reshape(1, -1, 3), code[:1]).reshape(7, 5)
    assert torch.allclose(net(x, code[0]), -logits, atol=1e-6)
    shifted = OccupancyNetwork(net.encoder, net.decoder, threshold=0.2).eval()
    assert torch.allclose(shifted(x, code[0]), np.log(0.25) - logits, atol=1e-5)
    # in eval mode the field of a point does not depend on the other points evaluated with it
    assert torch.allclose(net(x[:2], code[0]), net(x, code[0])[:2], atol=1e-6)
    with pytest.raises(InputError, match="encode a cloud"):
        net(x)
    cloud = torch.rand(50, 3) - 0.5
    cloud[7, 2] = float("inf")
    with pytest.raises(InputError, match="NaN or inf in 1 of its 50 points"):
        net.field_from_cloud(cloud)
    with pytest.raises(InputError, match=r"\(n >= 1, 3\), got \(50, 2\)"):
        net.field_from_cloud(cloud[:, :2])


def test_collection_sdf_batches_and_terms(collection):
    observation = CollectionSDF(collection, shapes_per_batch=5, samples_per_shape=64)
    assert [p.name for p in observation.paths] == [f"{r.name}.npz" for r in RECORDS]
    sampler = observation.prepare(Normalization(), 0.55, torch.device("cpu"), 0)
    batch = sampler.sample(torch.Generator().manual_seed(0))
    assert batch.points.shape == (2, 64, 3) and batch.sdf.shape == (2, 64)
    assert sorted(batch.shape_index.tolist()) == [0, 1]  # distinct shapes, all of them when fewer than asked
    for row, index in enumerate(batch.shape_index.tolist()):  # each sample with its own shape's distance
        arrays = load_cache(cache_path(collection, RECORDS[index]))
        pool = {tuple(p) for p in arrays["sdf_points"].tolist()}
        assert all(tuple(p) in pool for p in batch.points[row].tolist())
    torch.manual_seed(0)
    model = AutoDecoder(SDFMLP(width=32, depth=2, skip_layers=(), latent_dim=4), LatentCodes(2, 4))
    terms = sampler.losses(model, batch)
    codes = model.codes.weight[batch.shape_index]
    expected = clamped_l1(model.decoder(batch.points, codes[:, None].expand(2, 64, 4)).reshape(-1),
                          batch.sdf.reshape(-1), 0.1)
    assert torch.allclose(terms["sdf"], expected)
    assert torch.allclose(terms["code"], codes.square().sum(-1).mean())
    with pytest.raises(ConfigError, match="one code per shape"):
        sampler.losses(AutoDecoder(model.decoder, LatentCodes(3, 4)), batch)


def _numbered_caches(folder, count=4, rows=100):
    """Caches whose SDF values name their shape and point: value = sum of the point + 10 x shape."""
    paths = []
    for index in range(count):
        points = np.random.default_rng(index).random((rows, 3), dtype=np.float32)
        paths.append(write_npz(folder / f"s{index}.npz", {"sdf_points": points,
                                                          "sdf_values": points.sum(-1) + np.float32(10 * index)}))
    return paths


def test_draw_shape_sdf_is_repeatable_and_reads_each_point_with_its_value(tmp_path):
    paths = _numbered_caches(tmp_path)
    arrays = SplitArrays(paths, ("sdf_points", "sdf_values"))
    assert len(arrays) == 4 and arrays.rows("sdf_values") == 100
    a = draw_shape_sdf(arrays, Normalization(), 3, 10, torch.Generator().manual_seed(1))
    b = draw_shape_sdf(arrays, Normalization(), 3, 10, torch.Generator().manual_seed(1))
    assert torch.equal(a.points, b.points) and torch.equal(a.shape_index, b.shape_index)
    assert len(set(a.shape_index.tolist())) == 3
    assert torch.allclose(a.sdf, a.points.sum(-1) + 10 * a.shape_index[:, None])
    # the rows the generator names: the same draw over the stacked arrays in memory
    generator = torch.Generator().manual_seed(1)
    shape_index = torch.randperm(4, generator=generator)[:3]
    sample_index = torch.randint(100, (3, 10), generator=generator)
    stacked = torch.stack([torch.from_numpy(np.load(p)["sdf_points"]) for p in paths])
    assert torch.equal(a.points, stacked[shape_index[:, None], sample_index])
    # another frame: points mapped into it, distances scaled
    frame = Normalization(torch.tensor([0.5, 0.5, 0.5], dtype=torch.float64), 2.0)
    c = draw_shape_sdf(arrays, frame, 3, 10, torch.Generator().manual_seed(1))
    assert torch.allclose(c.points, (a.points - 0.5) / 2) and torch.allclose(c.sdf, a.sdf / 2)


def test_each_rank_reads_its_own_rows_of_the_global_batch(collection):
    """Two ranks of a global batch: disjoint shapes, together the batch one process draws, row for row
    (rank r keeps rows r::2), for both priors' samplers and every kind of input cloud."""
    records = [ShapeRecord("lamp", "train", i) for i in range(2)] + [ShapeRecord("chair", "train", i) for i in range(2)]
    root = collection.parent / "four_shapes"
    build_collection(root, records, RECIPE, progress=False)
    observations = [CollectionSDF(root, shapes_per_batch=4, samples_per_shape=32)] + [
        CollectionOccupancy(root, shapes_per_batch=4, query_points=20, cloud_points=16, **options)
        for options in ({"partial": 0.5}, {"partial": 1.0, "partial_views": 2}, {"near_fraction": 0.5})]
    for observation in observations:
        single = observation.prepare(Normalization(), 0.55, torch.device("cpu"), 0)
        whole = single.sample(torch.Generator().manual_seed(3))
        parts = [dataclasses.replace(single, rank=rank, world=2).sample(torch.Generator().manual_seed(3))
                 for rank in range(2)]
        for f in dataclasses.fields(whole):
            for rank, part in enumerate(parts):
                assert torch.equal(getattr(part, f.name), getattr(whole, f.name)[rank::2]), (observation, f.name)
    shapes = [set(part.shape_index.tolist()) for part in
              (dataclasses.replace(observations[0].prepare(Normalization(), 0.55, torch.device("cpu"), 0), rank=r,
                                   world=2).sample(torch.Generator().manual_seed(3)) for r in range(2))]
    assert not shapes[0] & shapes[1] and shapes[0] | shapes[1] == {0, 1, 2, 3}


def test_split_arrays_refuse_caches_of_other_recipes_and_compressed_members(tmp_path):
    paths = _numbered_caches(tmp_path, count=2)
    write_npz(tmp_path / "short.npz", {"sdf_points": np.zeros((50, 3), np.float32), "sdf_values": np.zeros(50, np.float32)})
    with pytest.raises(FileFormatError, match="other recipes"):
        SplitArrays([*paths, tmp_path / "short.npz"], ("sdf_points", "sdf_values"))
    write_npz(tmp_path / "packed.npz", {"sdf_points": np.zeros((100, 3), np.float32)}, compressed=True)
    with pytest.raises(FileFormatError, match="compressed"):
        SplitArrays([tmp_path / "packed.npz"], ("sdf_points",))
    with pytest.raises(FileFormatError, match="lacks 'sdf_normals'"):
        SplitArrays(paths, ("sdf_normals",))


def test_collection_occupancy_batches_carry_the_cached_labels(collection):
    observation = CollectionOccupancy(collection, shapes_per_batch=2, query_points=200, cloud_points=50,
                                      cloud_noise=0.0, partial=1.0)
    sampler = observation.prepare(Normalization(), 0.55, torch.device("cpu"), 0)
    batch = sampler.sample(torch.Generator().manual_seed(0))
    assert batch.clouds.shape == (2, 50, 3) and batch.points.shape == (2, 200, 3) and batch.inside.shape == (2, 200)
    # labels are the cache's: look each query point up in its shape's pools
    labelled = {}
    for record in RECORDS:
        arrays = load_cache(cache_path(collection, record))
        for kind in ("uniform", "near"):
            labelled.update(zip(map(tuple, arrays[f"occ_{kind}_points"].tolist()),
                                arrays[f"occ_{kind}_inside"].tolist()))
    for points, inside in zip(batch.points, batch.inside):
        assert [labelled[tuple(p)] for p in points.tolist()] == inside.bool().tolist()
    # one-sided clouds: without noise, every point is a surface sample seen from one side
    assert sampler.losses(OccupancyNetwork(PointNetEncoder(8, 8), CBNDecoder(8, 16)), batch)["occupancy"] > 0


def test_view_clouds_are_one_sided_surface_points_of_each_view():
    """A sphere of radius 0.4 seen by the one-view scene's cameras: every point lies on it, and each
    view sees one cap (all points within 90 deg of the view's mean direction)."""
    import trimesh

    ball = trimesh.creation.icosphere(subdivisions=4, radius=0.4)
    mesh = Mesh(torch.from_numpy(ball.vertices), torch.from_numpy(ball.faces))
    clouds = view_clouds([mesh, mesh], views=3, points_per_view=500, seed=0)
    assert clouds.shape == (2, 3, 500, 3)
    assert torch.allclose(clouds.norm(dim=-1), torch.full((2, 3, 500), 0.4), atol=2e-3)
    directions = torch.nn.functional.normalize(clouds, dim=-1)
    mean = torch.nn.functional.normalize(directions.mean(2, keepdim=True), dim=-1)
    assert ((directions * mean).sum(-1) > 0).all()
    assert not torch.allclose(mean[0, 0], mean[0, 1], atol=0.1)  # views from other sides


def test_one_sided_clouds_come_from_the_shapes_views(collection):
    observation = CollectionOccupancy(collection, shapes_per_batch=2, query_points=10, cloud_points=50,
                                      cloud_noise=0.0, partial=1.0, partial_views=2)
    sampler = observation.prepare(Normalization(), 0.55, torch.device("cpu"), 0)
    views = torch.from_numpy(np.load(sampler.views.path))  # rendered once, a shape at a time, into <root>/views/
    assert sampler.views.path.parent == collection / "views" and views.shape == (2, 2, 200, 3)
    meshes = [load_cache(cache_path(collection, record)) for record in RECORDS]
    meshes = [Mesh(torch.from_numpy(m["mesh_vertices"]).double(), torch.from_numpy(m["mesh_faces"])) for m in meshes]
    assert torch.equal(views, view_clouds(meshes, 2, 200, seed=0))  # the views of all shapes rendered at once
    assert observation.prepare(Normalization(), 0.55, torch.device("cpu"), 0).views == sampler.views  # reused
    batch = sampler.sample(torch.Generator().manual_seed(0))
    seen = [{tuple(p) for p in view.tolist()} for view in views.reshape(4, 200, 3)]
    for cloud in batch.clouds:
        owners = [all(tuple(p) in points for p in cloud.tolist()) for points in seen]
        assert sum(owners) == 1  # every point from one view of one shape


def test_one_shape_code_recovers_each_training_shape(collection, auto_decoder):
    """Each training code gives back its own shape (IoU on the cached uniform labels), and not the
    other one's: the decoder learned a prior over the collection, not one shape."""
    model = auto_decoder.model
    history = auto_decoder.history["shapes/sdf"]
    assert history[-1] < 0.6 * history[0]
    with torch.no_grad():
        for index, record in enumerate(RECORDS):
            points, inside = _uniform_labels(collection, record)
            own = _label_iou(model(points, model.codes.weight[index]), inside)
            other = _label_iou(model(points, model.codes.weight[1 - index]), inside)
            assert own > 0.7, (record.name, own)
            assert other < 0.3, (record.name, other)


def test_latent_fit_from_a_shapes_own_samples_returns_to_the_trained_codes_quality(collection, auto_decoder):
    model = auto_decoder.model
    decoder_state = {k: v.clone() for k, v in model.decoder.state_dict().items()}
    record, index = RECORDS[0], 0
    observation = SDFSampleSet.from_cache(cache_path(collection, record), batch_size=2048)
    result = reconstruct_latent(model.decoder, [observation], steps=120, lr=2e-2, seed=0)
    assert all(torch.equal(v, model.decoder.state_dict()[k]) for k, v in decoder_state.items())  # frozen
    fitted = result.model.code.detach()
    points, values = observation.points, observation.sdf
    points_u, inside = _uniform_labels(collection, record)
    with torch.no_grad():
        trained_code = model.codes.weight[index]
        loss = {name: clamped_l1(model.decoder(points, code), values, 0.1).item()
                for name, code in (("fitted", fitted), ("trained", trained_code), ("other", model.codes.weight[1]),
                                   ("zero", torch.zeros(8)))}
        iou_fitted = _label_iou(model.decoder(points_u, fitted), inside)
        iou_trained = _label_iou(model.decoder(points_u, trained_code), inside)
    assert loss["fitted"] <= 1.15 * loss["trained"], loss
    assert loss["fitted"] < 0.5 * min(loss["other"], loss["zero"]), loss
    assert iou_fitted > iou_trained - 0.05, (iou_fitted, iou_trained)


def test_completion_from_a_noisy_cloud_returns_the_shape_it_was_drawn_from(collection, auto_decoder):
    """complete_cloud (the latent fit of train.py's scores): the chair's 2,000 cached surface points
    with noise 0.005 give back the chair about as well as its trained code does, and not the lamp."""
    model = auto_decoder.model
    record, index = RECORDS[1], 1
    surface = torch.from_numpy(load_cache(cache_path(collection, record))["surface_points"]).double()
    field = complete_cloud(model, noisy_cloud(surface, 2000, 0.005, seed=0), latent_steps=150)
    points, inside = _uniform_labels(collection, record)
    lamp_points, lamp_inside = _uniform_labels(collection, RECORDS[0])
    with torch.no_grad():
        iou = _label_iou(field(points.double()), inside)
        iou_trained = _label_iou(model(points, model.codes.weight[index]), inside)
        iou_lamp = _label_iou(field(lamp_points.double()), lamp_inside)
    assert iou > iou_trained - 0.1, (iou, iou_trained)
    assert iou_lamp < 0.3, iou_lamp


def test_latent_prior_pulls_the_code_to_zero_and_needs_a_code():
    torch.manual_seed(0)
    decoder = SDFMLP(width=16, depth=2, skip_layers=(), latent_dim=3)
    model = LatentConditioned.from_code(decoder, torch.tensor([1.0, -2.0, 0.5]))
    result = fit(model, [LatentPrior({"code": 1.0})], steps=200, trainable=[model.code], encoding_lr=None,
                 normalization=Normalization(), progress=False,
                 optimizer=functools.partial(default_optimizer, lr=5e-2))
    assert result.model.code.norm() < 0.05
    with pytest.raises(ConfigError, match="LatentConditioned"):
        LatentPrior().prepare(Normalization(), 0.55, torch.device("cpu"), 0).losses(decoder, None)
    with pytest.raises(InputError, match="own code"):
        model(torch.zeros(2, 3), torch.zeros(3))


def test_eikonal_term_has_no_gradient_in_the_code_of_a_frozen_relu_decoder():
    """Why the one-view latent fit (`complete_view`) has no eikonal term: grad_x f of a ReLU decoder is
    piecewise constant in its code, so the term cannot move the code."""
    def code_gradients(activation: str) -> tuple[Tensor, Tensor]:
        torch.manual_seed(0)
        decoder = SDFMLP(width=32, depth=4, skip_layers=(2,), activation=activation, softplus_beta=10.0,
                         latent_dim=8, geometric_init=False).requires_grad_(False)  # code weights not zero
        model = LatentConditioned.from_code(decoder, 0.1 * torch.randn(8))
        points = (torch.rand(512, 3) - 0.5).requires_grad_(True)
        (gradient,) = torch.autograd.grad(model(points).sum(), points, create_graph=True)
        (of_eikonal,) = torch.autograd.grad(eikonal_loss(gradient), model.code)
        (of_values,) = torch.autograd.grad(model(points).square().mean(), model.code)
        return of_eikonal, of_values

    of_eikonal, of_values = code_gradients("relu")
    assert torch.count_nonzero(of_eikonal) == 0 and of_values.abs().min() > 0
    of_eikonal, _ = code_gradients("softplus")  # a smooth decoder's gradient does depend on the code
    assert of_eikonal.abs().min() > 0


@pytest.mark.slow
def test_occupancy_network_trained_on_two_shapes_recovers_them_from_their_clouds(collection):
    torch.manual_seed(0)
    net = OccupancyNetwork(PointNetEncoder(32, 32), CBNDecoder(32, 64, blocks=3))
    observation = CollectionOccupancy(collection, shapes_per_batch=2, query_points=1024, cloud_points=300)
    result = fit(net, observation, steps=300, normalization=Normalization(), encoding_lr=None, progress=False,
                 optimizer=functools.partial(default_optimizer, lr=1e-3), log_every=50)
    assert result.history["occupancy/occupancy"][-1] < 0.6 * result.history["occupancy/occupancy"][0]
    for record in RECORDS:
        arrays = load_cache(cache_path(collection, record))
        field = net.field_from_cloud(torch.from_numpy(arrays["surface_points"][:300]))
        points, inside = _uniform_labels(collection, record)
        with torch.no_grad():
            assert _label_iou(field(points.double()), inside) > 0.6


def test_load_prior_rebuilds_a_trained_prior_and_refuses_other_checkpoints(tmp_path, auto_decoder):
    from neuralsurf.checkpoints import load_checkpoint, save_checkpoint
    from neuralsurf.errors import CheckpointError
    from neuralsurf.priors import load_prior
    from neuralsurf.training import FitResult

    path = tmp_path / "prior.pt"
    auto_decoder.save(path)
    prior = load_prior(path)
    x = torch.rand(20, 3) - 0.5
    code = auto_decoder.model.codes.weight[0].detach()
    assert isinstance(prior, AutoDecoder) and not prior.training
    assert torch.equal(prior(x, code), auto_decoder.model.eval()(x, code))
    state = load_checkpoint(path)
    state["model_spec"]["arguments"]["codes"] = {"class": "os.system", "arguments": {"command": "echo"}}
    save_checkpoint(tmp_path / "crafted.pt", state)
    with pytest.raises(CheckpointError, match="not a neuralsurf model"):
        load_prior(tmp_path / "crafted.pt")
    single = SDFMLP(width=16, depth=2, skip_layers=())
    FitResult(single, Normalization(), auto_decoder.field).save(tmp_path / "single.pt")
    with pytest.raises(CheckpointError, match="not a learned prior"):
        load_prior(tmp_path / "single.pt")


def test_the_unit_frame_and_the_extraction_box_of_a_prior():
    from neuralsurf.priors import EXTRACTION_BOUNDS, UNIT_BOUNDS, CacheRecipe

    assert UNIT_BOUNDS.tolist() == [[-0.5] * 3, [0.5] * 3]
    padding = CacheRecipe().padding  # the caches' padding: ground-truth meshes and samples reach that far
    assert np.array_equal(EXTRACTION_BOUNDS, np.array([[-0.5 - padding] * 3, [0.5 + padding] * 3]))
    assert EXTRACTION_BOUNDS.tolist() == [[-0.55] * 3, [0.55] * 3]
