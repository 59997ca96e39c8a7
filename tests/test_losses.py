import pytest
import torch

from neuralsurf.errors import ConfigError
from neuralsurf.losses import clamped_l1, eikonal_loss, normal_loss
from neuralsurf.observations import PointSamples
from neuralsurf.observations.points import DEFAULT_POINT_WEIGHTS, evaluate_sdf_batch, point_terms
from neuralsurf.sampling import draw_batch, make_sdf_samples
from neuralsurf.scenes import Sphere


def batch_of(cloud):
    samples = make_sdf_samples(cloud, n_near=20_000, n_free=5000, seed=0)
    return draw_batch(samples, 2048, 0.25, torch.Generator().manual_seed(0))


@pytest.fixture(scope="module")
def batch(sphere_samples):
    """A batch of SDF samples of the analytic sphere's surface samples, normals included."""
    return batch_of(sphere_samples)


@pytest.fixture(scope="module")
def bare_batch(sphere_samples):
    """The same without normals."""
    return batch_of(sphere_samples.with_normals(None))


def test_exact_sphere_sdf_scores_about_zero(batch, sphere_field):
    terms = point_terms(evaluate_sdf_batch(sphere_field, batch), batch, DEFAULT_POINT_WEIGHTS)
    assert set(terms) == {"surface", "sdf", "normal", "eikonal"}
    assert terms["surface"] < 1e-6
    assert terms["normal"] < 1e-6
    assert terms["eikonal"] < 1e-6
    # the targets are nearest-neighbour estimates: small but not exactly zero
    assert terms["sdf"] < 2e-3


def test_wrong_sphere_scores_its_error(batch, analytic_field):
    terms = point_terms(evaluate_sdf_batch(analytic_field(Sphere(radius=0.35).sdf), batch), batch, DEFAULT_POINT_WEIGHTS)
    assert terms["surface"].item() == pytest.approx(0.05, abs=1e-5)


def test_without_near_gradient_the_values_match_and_grad_f_covers_surface_and_free_points(batch, sphere_field):
    torch.manual_seed(0)
    model = torch.nn.Sequential(torch.nn.Linear(3, 16), torch.nn.Softplus(beta=10), torch.nn.Linear(16, 1),
                                torch.nn.Flatten(0))
    full, lean = evaluate_sdf_batch(model, batch), evaluate_sdf_batch(model, batch, near_gradient=False)
    for name in ("surface", "near", "free", "surface_gradient"):
        assert torch.allclose(getattr(lean, name), getattr(full, name), atol=1e-6)
    n, m = len(batch.surface_points), len(batch.near_points)
    assert torch.allclose(lean.gradient, torch.cat([full.gradient[:n], full.gradient[n + m :]]), atol=1e-6)
    exact = point_terms(evaluate_sdf_batch(sphere_field, batch, near_gradient=False), batch, DEFAULT_POINT_WEIGHTS)
    assert exact["eikonal"] < 1e-6 and exact["normal"] < 1e-6
    terms = point_terms(lean, batch, DEFAULT_POINT_WEIGHTS)
    sum(terms.values()).backward()  # the near samples' sdf term reaches the weights by a first-order pass
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in model.parameters())


def test_terms_without_normals_and_weights_switch_terms_off(bare_batch, sphere_field):
    weights = {**DEFAULT_POINT_WEIGHTS, "normal": 0.5, "eikonal": 0.0, "off_surface": 1.0}
    terms = point_terms(evaluate_sdf_batch(sphere_field, bare_batch), bare_batch, weights)
    assert set(terms) == {"surface", "off_surface"}  # no normals: no sdf and normal terms


def test_loss_primitives_on_hand_made_values():
    assert clamped_l1(torch.tensor([0.5, 0.0]), torch.tensor([0.2, 0.05]), clamp=0.1) == pytest.approx(0.025)
    assert eikonal_loss(torch.tensor([[3.0, 4.0, 0.0]])) == pytest.approx(16.0)
    assert normal_loss(torch.tensor([[0.0, 0.0, 2.0]]), torch.tensor([[0.0, 0.0, -1.0]])) == pytest.approx(2.0)


def test_bad_weights_are_reported(sphere, bare_batch, sphere_field):
    cloud = sphere.sample_surface(100, seed=1)
    with pytest.raises(ConfigError, match=">= 0"):
        PointSamples(cloud, weights={"surface": -1.0})
    with pytest.raises(ConfigError, match="no loss term"):
        PointSamples(cloud, weights={"surfce": 1.0})
    with pytest.raises(ConfigError, match="at least one"):
        PointSamples(cloud, weights={name: 0.0 for name in DEFAULT_POINT_WEIGHTS})
    with pytest.raises(ConfigError, match="lacks its data"):
        point_terms(evaluate_sdf_batch(sphere_field, bare_batch), bare_batch, {"normal": 1.0})


def test_the_point_loss_has_the_parameter_gradients_finite_differences_give_in_float64(sphere):
    """gradcheck of the fit's weighted point loss (every term on, grad f inside the normal and eikonal
    terms, so the backward is a double backward) with respect to a small SDFMLP's weights, on an
    analytic sphere's samples."""
    from torch.func import functional_call

    from neuralsurf.models import SDFMLP
    from neuralsurf.sampling import SDFBatch

    torch.manual_seed(0)
    model = SDFMLP(width=8, depth=2, skip_layers=(), weight_norm=False, softplus_beta=10.0).double()
    generator = torch.Generator().manual_seed(0)
    surface = sphere.sample_surface(6, seed=2)
    near = surface.points + 0.02 * torch.randn(6, 3, dtype=torch.float64, generator=generator)
    free = torch.rand(4, 3, dtype=torch.float64, generator=generator) - 0.5
    batch = SDFBatch(surface.points, surface.normals, near, free, sphere.sdf(near), sphere.sdf(free))
    weights = {"surface": 3.0, "sdf": 1.0, "normal": 0.1, "eikonal": 0.1, "off_surface": 0.5}
    names = [name for name, _ in model.named_parameters()]

    def loss(*parameters):
        field = lambda x: functional_call(model, dict(zip(names, parameters)), (x,))
        terms = point_terms(evaluate_sdf_batch(field, batch), batch, weights, clamp=0.1, off_surface_alpha=10.0)
        assert list(terms) == list(weights)
        return sum(weights[name] * value for name, value in terms.items())

    parameters = tuple(p.detach().clone().requires_grad_(True) for p in model.parameters())
    assert all(p.dtype == torch.float64 for p in parameters)
    assert torch.autograd.gradcheck(loss, parameters, eps=1e-6, atol=1e-6)
