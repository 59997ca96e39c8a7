"""Synthetic depth scanner: exact z-depth against analytic oracles, camera placement, noise models."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from neuralsurf.cameras import backproject_depth, kinect_sigma, project_points
from neuralsurf.errors import ConfigError, InputError
from neuralsurf.geometry import point_to_mesh_distance
from neuralsurf.scenes import Sphere, look_at, orbit_cameras, scan_depth
from neuralsurf.scenes.scanner import depth_edges, fibonacci_sphere, intrinsics_from_fov
from neuralsurf.structures import DepthFrames, Mesh

SPHERE = Sphere(center=(0.1, -0.2, 1.5), radius=0.3)
K_SMALL = torch.tensor([[60.0, 0.0, 31.5], [0.0, 60.0, 23.5], [0.0, 0.0, 1.0]])


@pytest.fixture(scope="module")
def sphere_mesh() -> Mesh:
    return SPHERE.mesh(subdivisions=4)


def wall(z: float = 1.0, half: float = 10.0) -> Mesh:
    """A square facing the camera at the origin: every ray hits it at z-depth `z`."""
    v = [[-half, -half, z], [half, -half, z], [half, half, z], [-half, half, z]]
    return Mesh(torch.tensor(v, dtype=torch.float64), torch.tensor([[0, 1, 2], [0, 2, 3]]))


def test_depth_is_z_depth_not_ray_length():
    frames = scan_depth(wall(1.25), cam_to_world=torch.eye(4), K=K_SMALL, width=64, height=48)
    assert isinstance(frames, DepthFrames) and frames.depth.shape == (1, 48, 64)
    assert frames.depth.dtype == torch.float32
    torch.testing.assert_close(frames.depth, torch.full((1, 48, 64), 1.25), atol=2e-6, rtol=0)


def test_back_projected_depth_lies_on_the_mesh(sphere_mesh):
    frames = scan_depth(sphere_mesh, n_views=3, width=64, height=48)
    valid = frames.depth > 0
    assert valid.float().mean() > 0.2
    points = backproject_depth(frames)[valid].double()
    assert float(point_to_mesh_distance(points, sphere_mesh).max()) < 1e-5


def test_misses_are_zero_and_the_silhouette_matches_the_sphere():
    center = torch.tensor([0.0, 0.0, 2.0])
    frames = scan_depth(
        Sphere(tuple(center.tolist()), 0.5).mesh(5), cam_to_world=torch.eye(4), K=K_SMALL, width=64, height=48
    )
    v, u = torch.meshgrid(torch.arange(48.0), torch.arange(64.0), indexing="ij")
    rays = torch.nn.functional.normalize(
        torch.stack([(u - 31.5) / 60, (v - 23.5) / 60, torch.ones_like(u)], -1), dim=-1
    )
    distance_to_axis = torch.linalg.cross(rays, center.expand_as(rays)).norm(dim=-1)  # ray-centre distance
    clear_hit, clear_miss = distance_to_axis < 0.48, distance_to_axis > 0.5
    assert (frames.depth[0][clear_hit] > 0).all() and (frames.depth[0][clear_miss] == 0).all()


def test_orbit_cameras_look_at_the_centre_from_the_distance(sphere_mesh):
    frames = scan_depth(sphere_mesh, n_views=8, width=80, height=60, distance=2.0)
    center = torch.tensor(SPHERE.center)
    eye = frames.cam_to_world[:, :3, 3].double()
    torch.testing.assert_close(
        (eye - center).norm(dim=-1), torch.full((8,), 2.0, dtype=torch.float64), atol=1e-5, rtol=0
    )
    uv, z = project_points(center.float().expand(8, 1, 3), frames.K, frames.cam_to_world)
    torch.testing.assert_close(uv[:, 0], torch.tensor([39.5, 29.5]).expand(8, 2), atol=1e-3, rtol=0)
    assert (z > 0).all()


def test_default_distance_keeps_the_whole_object_in_view(sphere_mesh):
    frames = scan_depth(sphere_mesh, n_views=6, width=64, height=48, fov_deg=50)
    uv, z = project_points(sphere_mesh.vertices.float().expand(6, -1, -1), frames.K, frames.cam_to_world)
    assert (z > 0).all()
    assert (uv[..., 0] >= -0.5).all() and (uv[..., 0] <= 63.5).all()
    assert (uv[..., 1] >= -0.5).all() and (uv[..., 1] <= 47.5).all()
    assert (frames.depth > 0).float().mean() > 0.3  # and fills a good part of it


def test_look_at_follows_opencv_axes():
    pose = look_at(eye=(0.0, 0.0, -3.0), target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0))
    torch.testing.assert_close(pose[:3, 2], torch.tensor([0.0, 0, 1], dtype=torch.float64))  # z forward
    torch.testing.assert_close(pose[:3, 1], torch.tensor([0.0, -1, 0], dtype=torch.float64))  # y down
    torch.testing.assert_close(pose[:3, 0], torch.linalg.cross(pose[:3, 1], pose[:3, 2]))  # right-handed
    straight_down = look_at(eye=(0.0, 5.0, 0.0), target=(0.0, 0.0, 0.0))  # parallel to up: still a rotation
    rotation = straight_down[:3, :3]
    torch.testing.assert_close(rotation.T @ rotation, torch.eye(3, dtype=torch.float64))
    assert float(torch.linalg.det(rotation)) == pytest.approx(1.0)


def test_fibonacci_directions_are_unit_and_spread():
    d = fibonacci_sphere(200)
    torch.testing.assert_close(d.norm(dim=-1), torch.ones(200, dtype=torch.float64))
    assert d.mean(0).norm() < 0.02
    nearest = (d[:, None] - d[None]).norm(dim=-1).add(torch.eye(200) * 9).min(1).values
    assert float(nearest.min()) > 0.5 * math.sqrt(4 * math.pi / 200)
    assert orbit_cameras((0, 0, 0), 1.0, 5, 60.0, 4 / 3).shape == (5, 4, 4)


def test_gaussian_noise_has_the_requested_sigma():
    clean = scan_depth(wall(), cam_to_world=torch.eye(4), K=K_SMALL, width=64, height=48)
    noisy = scan_depth(
        wall(),
        cam_to_world=torch.eye(4),
        K=K_SMALL,
        width=64,
        height=48,
        noise="gaussian",
        sigma=0.004,
        seed=3,
    )
    residual = noisy.depth - clean.depth
    assert float(residual.std()) == pytest.approx(0.004, rel=0.05)
    assert abs(float(residual.mean())) < 0.0005


def test_kinect_noise_follows_the_axial_model():
    far = scan_depth(wall(3.0), cam_to_world=torch.eye(4), K=K_SMALL, width=64, height=48, noise="kinect")
    inner = far.depth[0, 2:-2, 2:-2]  # a flat wall: no edges, no grazing angles, no dropout
    assert (inner > 0).all()
    assert float((inner - 3.0).std()) == pytest.approx(float(kinect_sigma(torch.tensor(3.0))), rel=0.08)
    assert float(kinect_sigma(torch.tensor(0.4))) == pytest.approx(0.0012)


def test_kinect_drops_grazing_angles_and_depth_edges(sphere_mesh):
    frames = scan_depth(
        sphere_mesh,
        cam_to_world=look_at((0.1, -0.2, 0.5), SPHERE.center)[None],
        K=K_SMALL,
        width=64,
        height=48,
    )
    kinect = scan_depth(
        sphere_mesh,
        cam_to_world=frames.cam_to_world,
        K=K_SMALL,
        width=64,
        height=48,
        noise="kinect",
        max_angle_deg=60.0,
    )
    clean, kept = frames.depth[0], kinect.depth[0] > 0
    assert kept.sum() < (clean > 0).sum()
    assert not (kept & depth_edges(frames.depth, 0.03)[0]).any()  # nothing kept next to the silhouette
    # a sphere seen from its axis: the incidence angle grows with the distance of the ray from the centre
    eye, center = frames.cam_to_world[0, :3, 3].double(), torch.tensor(SPHERE.center)
    points = backproject_depth(frames)[0].double()
    normals = torch.nn.functional.normalize(points - center, dim=-1)
    rays = torch.nn.functional.normalize(points - eye, dim=-1)
    cosine = (normals * rays).sum(-1).abs()
    assert not (kept & (cosine < math.cos(math.radians(61)))).any()
    assert kept[(clean > 0) & (cosine > math.cos(math.radians(50)))].float().mean() > 0.95


def test_noise_is_deterministic_for_a_seed(sphere_mesh):
    a = scan_depth(sphere_mesh, n_views=2, width=32, height=24, noise="kinect", seed=5)
    b = scan_depth(sphere_mesh, n_views=2, width=32, height=24, noise="kinect", seed=5)
    c = scan_depth(sphere_mesh, n_views=2, width=32, height=24, noise="kinect", seed=6)
    assert torch.equal(a.depth, b.depth) and not torch.equal(a.depth, c.depth)


def test_intrinsics_from_fov():
    K = intrinsics_from_fov(320, 240, 60.0)
    assert float(K[1, 1]) == pytest.approx(120 / math.tan(math.radians(30)))
    assert (float(K[0, 2]), float(K[1, 2])) == (159.5, 119.5)


def test_bad_input_is_explained(sphere_mesh):
    with pytest.raises(InputError, match="Mesh"):
        scan_depth(np.zeros((3, 3)))
    with pytest.raises(ConfigError, match="noise must be one of"):
        scan_depth(sphere_mesh, noise="salt")
    with pytest.raises(ConfigError, match="sigma"):
        scan_depth(sphere_mesh, noise="kinect", sigma=0.01)
    bad_K = K_SMALL.clone()
    bad_K[0, 2] = 320.0  # calibrated for a 640-wide image
    with pytest.raises(InputError, match="principal point"):
        scan_depth(sphere_mesh, K=bad_K, width=64, height=48)
    with pytest.raises(InputError, match="cam_to_world"):
        scan_depth(sphere_mesh, cam_to_world=torch.eye(3))
