import itertools

import pytest
import torch

from neuralsurf.errors import ConfigError, InputError
from neuralsurf.models import SDFMLP, FourierFeatures, HashGrid, NormalizedField
from neuralsurf.scenes import Sphere
from neuralsurf.structures import Normalization


def grid_points(n: int = 4000, seed: int = 0) -> torch.Tensor:
    return torch.rand(n, 3, generator=torch.Generator().manual_seed(seed)) - 0.5


@pytest.mark.parametrize("encoding", [None, FourierFeatures(4), HashGrid(levels=4, log2_table_size=12, max_resolution=64)])
@pytest.mark.parametrize("latent_dim", [0, 8])
def test_forward_shapes(encoding, latent_dim):
    model = SDFMLP(width=64, depth=4, skip_layers=(2,), encoding=encoding, latent_dim=latent_dim)
    latent = torch.zeros(latent_dim) if latent_dim else None
    assert model(torch.zeros(5, 7, 3), latent).shape == (5, 7)
    assert model(torch.zeros(3), latent).shape == ()


@pytest.mark.parametrize("activation", ["relu", "softplus"])
def test_geometric_init_is_close_to_a_sphere(activation, sphere):
    torch.manual_seed(0)
    model = SDFMLP(width=256, depth=4, skip_layers=(2,), activation=activation, init_radius=0.3)
    x = grid_points()
    f = model(x).detach()
    truth = sphere.sdf(x)
    # sign agreement away from the sphere and a strong linear relation to |x|
    far = truth.abs() > 0.1
    assert ((f[far] < 0) == (truth[far] < 0)).float().mean() > 0.97
    assert torch.corrcoef(torch.stack([f, truth]))[0, 1] > 0.9


def test_gradient_exists_and_matches_finite_differences():
    torch.manual_seed(0)
    model = SDFMLP(width=32, depth=3, skip_layers=(), activation="softplus", weight_norm=False).double()
    x = grid_points(10).double().requires_grad_(True)
    (g,) = torch.autograd.grad(model(x).sum(), x)
    eps = 1e-6
    for axis in range(3):
        step = torch.zeros(3, dtype=torch.float64)
        step[axis] = eps
        fd = (model(x + step) - model(x - step)) / (2 * eps)
        assert torch.allclose(g[:, axis], fd.detach(), atol=1e-6)


@pytest.mark.parametrize("options", [{"levels": 8, "log2_table_size": 17, "max_resolution": 256},  # int32
                                     {"levels": 4, "log2_table_size": 22, "max_resolution": 1024}])  # int64
def test_hashgrid_rows_are_the_dense_index_or_teschner_hash_of_each_corner(options):
    grid = HashGrid(**options)
    x = torch.rand(500, 3) * 1.4 - 0.7  # some outside the bound: clamped
    resolution = grid.resolution.flatten()[None, :, None]
    position = ((x.clamp(-0.6, 0.6) + 0.6) / 1.2)[:, None, :] * resolution  # [n, L, 3]
    low = position.floor().minimum(resolution - 1).long()
    rows = grid._rows(low.permute(1, 2, 0).int()).long()  # [n, L, 2, 2, 2]
    table, offset = 2 ** options["log2_table_size"], 0
    for level, resolution in enumerate(grid.resolution.flatten().tolist()):
        for corner in itertools.product((0, 1), repeat=3):
            i, j, k = (low[:, level] + torch.tensor(corner)).unbind(-1)
            side = resolution + 1
            if side**3 <= table:
                expected = (i * side + j) * side + k
            else:  # Teschner et al.'s spatial hash, as Instant-NGP (int64: no overflow before the mask)
                expected = (i * 1 ^ j * 2_654_435_761 ^ k * 805_459_861) % table
            assert torch.equal(rows[:, level][:, corner[0], corner[1], corner[2]], expected + offset)
        offset += min(side**3, table)


def test_hashgrid_is_twice_differentiable_gradcheck():
    torch.manual_seed(0)
    grid = HashGrid(levels=2, log2_table_size=8, base_resolution=4, max_resolution=20, init_scale=0.1).double()
    x = (grid_points(4).double() * 0.9).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda p: grid(p)[:, 3:].sum(-1), (x,))
    assert torch.autograd.gradgradcheck(lambda p: grid(p)[:, 3:].sum(-1), (x,))


def test_sine_activation_runs_and_differs_from_relu():
    torch.manual_seed(0)
    x = grid_points(100)
    siren = SDFMLP(width=32, depth=3, skip_layers=(), activation="sine")
    assert torch.isfinite(siren(x)).all()
    assert not torch.allclose(siren(x), SDFMLP(width=32, depth=3, skip_layers=(), activation="relu")(x))


def test_normalized_field_maps_world_to_unit_and_scales_distance():
    sphere = Sphere(radius=0.4)
    norm = Normalization(center=torch.tensor([10.0, -2.0, 3.0]), scale=5.0)

    class Exact(torch.nn.Module):
        def forward(self, x, latent=None):
            return sphere.sdf(x)

    field = NormalizedField(Exact(), norm)
    world = norm.to_world(grid_points(100).double())
    expected = (world - norm.center).norm(dim=-1) - 0.4 * 5.0
    assert torch.allclose(field(world).double(), expected, atol=1e-4)
    assert torch.allclose(field.bounds, norm.to_world(torch.tensor([[-0.55] * 3, [0.55] * 3]).double()))


def test_bad_configuration_and_input_are_reported():
    with pytest.raises(ConfigError, match="activation"):
        SDFMLP(activation="tanh")
    with pytest.raises(ConfigError, match="skip_layers"):
        SDFMLP(depth=4, skip_layers=(4,))
    with pytest.raises(InputError, match="latent"):
        SDFMLP(width=32, depth=2, skip_layers=(), latent_dim=4)(torch.zeros(2, 3))
    with pytest.raises(InputError, match=r"\(\.\.\., 3\)"):
        SDFMLP(width=32, depth=2, skip_layers=())(torch.zeros(2, 2))
