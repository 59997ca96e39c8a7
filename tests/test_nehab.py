"""Nehab et al. 2005 fusion of depth and normals: noisy depth of a plane and of a sphere, with their
exact normals, comes out closer to the true depth than the measurement; then TSDF."""

import pytest
import torch

from neuralsurf.baselines.nehab import fuse_depth_normals, fuse_frames
from neuralsurf.cameras import pixel_rays
from neuralsurf.errors import ConfigError, InputError
from neuralsurf.structures import DepthFrames

W, H, F = 96, 72, 90.0
K = torch.tensor([[F, 0, (W - 1) / 2], [0, F, (H - 1) / 2], [0, 0, 1]], dtype=torch.float64)


def plane_view():
    """A tilted plane n . x = d in front of the camera: exact z-depth and camera-frame normals."""
    normal = torch.nn.functional.normalize(torch.tensor([0.3, -0.2, -1.0], dtype=torch.float64), dim=0)
    d = float(normal @ torch.tensor([0.0, 0.0, 1.2], dtype=torch.float64))  # through (0, 0, 1.2)
    rays = pixel_rays(K, H, W)
    z = d / (rays @ normal)
    return z, normal.expand(H, W, 3).clone()


def sphere_view(radius: float = 0.5, distance: float = 1.5):
    rays = pixel_rays(K, H, W)
    c = torch.tensor([0.0, 0.0, distance], dtype=torch.float64)
    a, b, cc = (rays * rays).sum(-1), -2 * (rays @ c), float(c @ c) - radius**2
    disc = b**2 - 4 * a * cc
    z = torch.where(disc > 0, (-b - disc.clamp_min(0).sqrt()) / (2 * a), 0.0)
    normals = torch.where((z > 0)[..., None], (z[..., None] * rays - c) / radius, 0.0)
    return z, normals


def noisy(z, sigma: float, seed: int = 0):
    noise = sigma * torch.randn(z.shape, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    return torch.where(z > 0, z + noise, 0.0)


@pytest.mark.parametrize("view", [plane_view, sphere_view])
def test_fusion_recovers_the_surface_better_than_the_noisy_depth(view):
    z, normals = view()
    measured = noisy(z, 0.005)
    fused = fuse_depth_normals(measured, normals, K, position_weight=0.05)
    valid = z > 0
    assert bool(((fused > 0) == valid).all())
    before = float((measured - z)[valid].abs().mean())
    after = float((fused - z)[valid].abs().mean())
    assert after < 0.25 * before, (before, after)


def test_exact_depth_and_normals_are_a_fixed_point():
    z, normals = plane_view()
    fused = fuse_depth_normals(z, normals, K, position_weight=0.1)
    assert float((fused - z).abs().max()) < 1e-9


def test_normals_alone_cannot_move_a_plane_with_no_tangent_rows():
    """position_weight = 1: the positions only, so the measurement comes back unchanged."""
    z, normals = plane_view()
    measured = noisy(z, 0.005)
    assert torch.allclose(fuse_depth_normals(measured, normals, K, position_weight=1.0), measured, atol=1e-9)


def test_zero_confidence_switches_the_normals_off():
    z, normals = sphere_view()
    measured = noisy(z, 0.005)
    fused = fuse_depth_normals(measured, normals, K, confidence=torch.zeros(H, W), position_weight=0.05)
    assert torch.allclose(fused, measured, atol=1e-9)


def test_fuse_frames_upsamples_half_resolution_depth_and_tsdf_meshes_it():
    from neuralsurf.baselines import TSDFVolume
    from neuralsurf.cameras import resample_depth

    z, normals = sphere_view()
    low = K.clone()
    low[0, 0], low[1, 1] = F / 2, F / 2
    low[0, 2], low[1, 2] = (K[0, 2] + 0.5) / 2 - 0.5, (K[1, 2] + 0.5) / 2 - 0.5
    rays = pixel_rays(low, H // 2, W // 2)
    c = torch.tensor([0.0, 0.0, 1.5], dtype=torch.float64)
    a, b, cc = (rays * rays).sum(-1), -2 * (rays @ c), float(c @ c) - 0.25
    disc = b**2 - 4 * a * cc
    z_low = torch.where(disc > 0, (-b - disc.clamp_min(0).sqrt()) / (2 * a), 0.0)
    measured = noisy(z_low, 0.005)
    frames = DepthFrames(measured[None].float(), low[None].float(), torch.eye(4)[None])
    fused = fuse_frames(frames, normals[None], K, position_weight=0.05)
    assert fused.depth.shape == (1, H, W)
    valid = fused.depth[0] > 0
    upsampled = resample_depth(measured, low, K, H, W)
    assert valid.sum() > 0.8 * (z > 0).sum()
    assert float((fused.depth[0].double() - z)[valid].abs().mean()) < 0.5 * float((upsampled - z)[valid].abs().mean())
    volume = TSDFVolume(torch.tensor([[-0.6, -0.6, 0.9], [0.6, 0.6, 2.1]]), 0.02, 0.06, device="cpu")
    mesh = volume.integrate(fused, progress=False).extract_mesh()
    distance = ((mesh.vertices.double() - c).norm(dim=-1) - 0.5).abs()
    assert len(mesh.faces) > 100 and float(distance.mean()) < 0.01


def test_bad_inputs_are_clear_errors():
    z, normals = plane_view()
    with pytest.raises(ConfigError, match="position_weight"):
        fuse_depth_normals(z, normals, K, position_weight=0.0)
    with pytest.raises(InputError, match="missing"):
        fuse_depth_normals(torch.zeros(H, W), normals, K)
    with pytest.raises(InputError, match="one normal map"):
        fuse_frames(DepthFrames(z[None].float(), K[None].float(), torch.eye(4)[None]), normals, K)
