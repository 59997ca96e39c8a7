"""Strategies chosen by name through the one registry: the names configs use still work, an unknown
name lists the choices, and a caller's own strategy object is used as it is."""

import pytest
import torch

from neuralsurf.errors import ConfigError
from neuralsurf.observations.points import estimated_normals, given_normals, no_normals, prepare_cloud
from neuralsurf.scenes import Sphere, scan_depth
from neuralsurf.scenes.scanner import NOISE_MODELS, gaussian_noise, kinect_noise, no_noise
from neuralsurf.strategies import choose, name_of, names
from neuralsurf.structures import Mesh

K = torch.tensor([[20.0, 0.0, 7.5], [0.0, 20.0, 5.5], [0.0, 0.0, 1.0]])


def wall(z: float = 1.0, half: float = 10.0) -> Mesh:
    """A square facing the camera at the origin: every ray hits it at z-depth `z`."""
    v = [[-half, -half, z], [half, -half, z], [half, half, z], [-half, half, z]]
    return Mesh(torch.tensor(v, dtype=torch.float64), torch.tensor([[0, 1, 2], [0, 2, 3]]))


def test_names_resolve_to_their_strategies_and_unknown_names_list_the_choices():
    assert NOISE_MODELS == names("depth noise") == ("none", "gaussian", "kinect")
    assert [choose("depth noise", n) for n in NOISE_MODELS] == [no_noise, gaussian_noise, kinect_noise]
    assert names("normal source") == ("given", "estimate", "ignore")
    assert choose("normal source", "ignore") is no_normals and name_of("normal source", given_normals) == "given"
    with pytest.raises(ConfigError, match=r"unknown normal source 'guess'; choose one of 'given', 'estimate'"):
        choose("normal source", "guess")
    own = object()
    assert choose("depth noise", own) is own and name_of("depth noise", own) is None


def test_a_noise_model_of_ones_own_replaces_the_named_ones():
    def offset(depth, cosine, generator, sigma, max_angle_deg, edge_jump):
        return torch.where(depth > 0, depth + 0.25, 0.0)

    frames = scan_depth(wall(1.0), cam_to_world=torch.eye(4), K=K, width=16, height=12, noise=offset)
    torch.testing.assert_close(frames.depth, torch.full((1, 12, 16), 1.25), atol=2e-6, rtol=0)
    with pytest.raises(ConfigError, match="noise must be one of"):
        scan_depth(wall(1.0), cam_to_world=torch.eye(4), K=K, width=16, height=12, noise="speckle")


def test_the_named_gaussian_noise_draws_from_the_seeded_generator():
    exact = scan_depth(wall(1.0), cam_to_world=torch.eye(4), K=K, width=16, height=12).depth
    noisy = scan_depth(wall(1.0), cam_to_world=torch.eye(4), K=K, width=16, height=12, noise="gaussian",
                       sigma=0.01, seed=3).depth
    expected = exact + 0.01 * torch.randn(exact.shape, generator=torch.Generator().manual_seed(3))
    torch.testing.assert_close(noisy, expected, atol=1e-6, rtol=0)


def test_a_normal_source_of_ones_own_supplies_the_fits_normals():
    sphere = Sphere(center=(0.5, 0.0, 0.0), radius=1.0)
    cloud = sphere.sample_surface(500, seed=0).with_normals(None)

    def radial(cloud, normal_k, denoise):  # the sphere's exact normals
        return cloud.with_normals(torch.nn.functional.normalize(cloud.points - cloud.points.new_tensor([0.5, 0, 0]),
                                                                dim=-1))

    prepared = prepare_cloud(cloud, radial, normal_k=10)
    assert torch.allclose(prepared.normals.double(), sphere.sample_surface(500, seed=0).normals.double(), atol=1e-6)
    estimated = prepare_cloud(cloud, "estimate", normal_k=10)
    assert estimated_normals is choose("normal source", "estimate")
    assert (estimated.normals.double() * prepared.normals.double()).sum(-1).min() > 0.9  # PCA + MST: outward too


def test_depth_rays_take_their_noise_sigma_from_the_registry():
    from neuralsurf.cameras import kinect_sigma
    from neuralsurf.observations import DepthRays

    z = torch.linspace(0.5, 4.0, 8)
    assert names("depth sigma") == ("kinect", "constant")
    assert torch.equal(choose("depth sigma", "kinect")(z, 0.002), kinect_sigma(z))
    assert torch.equal(choose("depth sigma", "constant")(z, 0.002), torch.full_like(z, 0.002))
    frames = scan_depth(wall(1.0), cam_to_world=torch.eye(4), K=K, width=16, height=12)
    DepthRays(frames, noise_model=lambda z, sigma: 2 * torch.full_like(z, sigma))  # one's own is accepted
    with pytest.raises(ConfigError, match="noise_model kinect or constant"):
        DepthRays(frames, noise_model="speckle")
