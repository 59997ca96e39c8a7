"""Back-projection of depth images, projection, and depth -> point cloud with normals."""

import math

import numpy as np
import pytest
import torch

from neuralsurf.cameras import backproject_depth, depth_to_cloud, project_points
from neuralsurf.errors import InputError
from neuralsurf.structures import DepthFrames

K = torch.tensor([[500.0, 0.0, 31.5], [0.0, 480.0, 23.5], [0.0, 0.0, 1.0]])
H, W = 48, 64


def rotation(axis, angle) -> torch.Tensor:
    axis = torch.nn.functional.normalize(torch.as_tensor(axis, dtype=torch.float64), dim=0)
    x = torch.tensor([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return torch.eye(3, dtype=torch.float64) + math.sin(angle) * x + (1 - math.cos(angle)) * x @ x


def pose(axis=(0, 1, 0), angle=0.0, t=(0.0, 0.0, 0.0)) -> torch.Tensor:
    out = torch.eye(4, dtype=torch.float64)
    out[:3, :3], out[:3, 3] = rotation(axis, angle), torch.as_tensor(t, dtype=torch.float64)
    return out


def render_plane(normal, offset, cam_to_world, K=K, h=H, w=W) -> torch.Tensor:
    """Exact z-depth (h, w) of the plane {x : normal . x = offset} (0 where it is not in front)."""
    n = torch.as_tensor(normal, dtype=torch.float64)
    v, u = torch.meshgrid(
        torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij"
    )
    K = K.double()
    rays = torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones_like(u)], -1)  # z = 1
    world_rays = rays @ cam_to_world[:3, :3].T
    depth = (offset - n @ cam_to_world[:3, 3]) / (world_rays @ n)
    return torch.where(depth > 0, depth, torch.zeros_like(depth)).float()


def render_sphere(center, radius, K=K, h=H, w=W) -> torch.Tensor:
    """Exact z-depth of a sphere seen by a camera at the origin (identity pose)."""
    c = torch.as_tensor(center, dtype=torch.float64)
    v, u = torch.meshgrid(
        torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij"
    )
    K = K.double()
    rays = torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones_like(u)], -1)
    a, b = (rays * rays).sum(-1), -2 * rays @ c
    disc = b * b - 4 * a * (c @ c - radius**2)
    t = (-b - disc.clamp(min=0).sqrt()) / (2 * a)
    return torch.where(disc > 0, t, torch.zeros_like(t)).float()


def test_pixel_centres_follow_opencv():
    depth = torch.full((1, H, W), 2.0)
    points = backproject_depth(DepthFrames(depth, K, torch.eye(4)))
    # K's principal point (31.5, 23.5) lies between pixel centres: (u, v) = (31, 23) is half a pixel
    # left of and above it
    assert torch.allclose(points[0, 23, 31], torch.tensor([-0.5 * 2 / 500, -0.5 * 2 / 480, 2.0]))
    # moving fx pixels right moves one unit of depth right; rows index v (y down)
    assert torch.allclose(points[0, 23, 31 + 10] - points[0, 23, 31], torch.tensor([10 * 2 / 500, 0, 0]))
    assert torch.allclose(points[0, 23 + 4, 31] - points[0, 23, 31], torch.tensor([0, 4 * 2 / 480, 0]))


def test_backprojected_points_lie_on_the_rendered_plane_and_project_back():
    normal, offset = (
        torch.nn.functional.normalize(torch.tensor([0.2, -0.3, 1.0], dtype=torch.float64), dim=0),
        3.0,
    )
    poses = torch.stack([pose((0, 1, 0), 0.1, (0.1, 0.0, 0.2)), pose((1, 1, 0), -0.2, (-0.3, 0.2, 0.0))])
    depth = torch.stack([render_plane(normal, offset, p) for p in poses])
    frames = DepthFrames(depth, K, poses.float())
    points = backproject_depth(frames)  # (2, h, w, 3)
    assert points.shape == (2, H, W, 3)
    valid = frames.depth > 0
    assert valid.float().mean() > 0.99
    assert torch.allclose(
        points[valid].double() @ normal, torch.tensor(offset, dtype=torch.float64), atol=1e-5
    )
    uv, z = project_points(points.reshape(2, -1, 3), frames.K, frames.cam_to_world)
    v, u = torch.meshgrid(
        torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32), indexing="ij"
    )
    assert torch.allclose(uv[0], torch.stack([u, v], -1).reshape(-1, 2), atol=1e-3)
    assert torch.allclose(z, frames.depth.reshape(2, -1), atol=1e-5)
    # single-camera form
    uv1, z1 = project_points(points[1].reshape(-1, 3), frames.K[1], frames.cam_to_world[1])
    assert torch.allclose(uv1, uv[1]) and torch.allclose(z1, z[1])


def test_backprojection_matches_open3d():
    o3d = pytest.importorskip("open3d")
    depth = render_plane((0.1, 0.2, 1.0), 2.0, pose())
    depth[5:9, 10:20] = 0  # holes are skipped by both
    intrinsic = o3d.camera.PinholeCameraIntrinsic(
        W, H, float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
    )
    cam_to_world = pose((0, 0, 1), 0.3, (1.0, 2.0, 3.0))
    theirs = o3d.geometry.PointCloud.create_from_depth_image(
        o3d.geometry.Image(depth.numpy()),
        intrinsic,
        np.linalg.inv(cam_to_world.numpy()),
        depth_scale=1.0,
        depth_trunc=100.0,
    )
    ours = depth_to_cloud(DepthFrames(depth, K, cam_to_world.float()), with_normals=False)
    assert len(ours) == len(theirs.points) == int((depth > 0).sum())
    assert np.allclose(ours.points.numpy(), np.asarray(theirs.points), atol=1e-5)


def test_plane_normals_face_the_camera():
    normal = torch.nn.functional.normalize(torch.tensor([0.3, 0.1, -1.0], dtype=torch.float64), dim=0)
    cam = pose((0, 1, 0), 0.2, (0.0, 0.0, 0.0))
    frames = DepthFrames(render_plane(normal, -2.0, cam), K, cam.float())
    cloud = depth_to_cloud(frames)
    expected = normal if float(normal @ (cam[:3, 3] - cloud.points[0].double())) > 0 else -normal
    assert len(cloud) == H * W  # one-sided differences cover the border
    assert torch.allclose(cloud.normals.double(), expected.expand(len(cloud), 3), atol=1e-3)
    camera_centre = cam[:3, 3].float()
    assert ((cloud.normals * (camera_centre - cloud.points)).sum(-1) > 0).all()


def test_sphere_normals_are_radial_and_edges_are_not_bridged():
    center, radius = torch.tensor([0.005, -0.003, 1.0]), 0.04
    sphere = render_sphere(center, radius)
    assert 0.2 < (sphere > 0).float().mean() < 0.8  # the silhouette lies inside the image
    depth = torch.where(sphere > 0, sphere, torch.full_like(sphere, 1.5))  # in front of a wall at z = 1.5
    cloud = depth_to_cloud(DepthFrames(depth, K, torch.eye(4)))
    assert H * W - 4 <= len(cloud) < H * W  # only silhouette tips lack a neighbour on their own surface
    on_sphere = cloud.points[:, 2] < 1.4
    radial = torch.nn.functional.normalize(cloud.points[on_sphere] - center, dim=-1)
    cosine = (cloud.normals[on_sphere] * radial).sum(-1)
    assert cosine.min() > 0.5  # outward (the camera is outside), even at the grazing silhouette
    assert cosine.median() > 0.999
    assert torch.quantile(cosine, 0.05) > 0.97
    # wall pixels next to the silhouette do not difference across the 0.5 m jump
    wall = cloud.normals[~on_sphere]
    assert torch.allclose(wall, torch.tensor([0.0, 0.0, -1.0]).expand_as(wall), atol=1e-5)
    bridged = depth_to_cloud(DepthFrames(depth, K, torch.eye(4)), max_depth_jump=1.0)
    assert (
        bridged.normals[bridged.points[:, 2] > 1.4, 2] > -0.99
    ).any()  # the threshold is what keeps them clean


def test_stride_holes_colours_and_isolated_pixels():
    depth = render_plane((0.0, 0.0, 1.0), 1.5, pose())
    depth[10:20, 10:20] = 0
    depth[30, 40] = 1.5  # isolated pixel: no valid neighbour left, right, up or down
    depth[29:32, 39:42] = 0
    depth[30, 40] = 1.5
    colors = torch.rand(1, H, W, 3, generator=torch.Generator().manual_seed(0))
    frames = DepthFrames(depth, K, torch.eye(4), colors)
    with_normals = depth_to_cloud(frames)
    without = depth_to_cloud(frames, with_normals=False)
    assert len(without) == int((depth > 0).sum())
    assert len(with_normals) == len(without) - 1  # only the isolated pixel has no normal
    assert without.normals is None
    assert torch.allclose(without.colors, colors[0][depth > 0])
    strided = depth_to_cloud(frames, stride=3, with_normals=False)
    assert len(strided) == int((depth[::3, ::3] > 0).sum())
    assert torch.allclose(strided.points, backproject_depth(frames)[0, ::3, ::3][depth[::3, ::3] > 0])
    # normals at the strided pixels are those computed at full resolution
    assert torch.allclose(
        depth_to_cloud(frames, stride=3).normals,
        torch.tensor([0.0, 0.0, -1.0]).expand(len(strided), 3),
        atol=1e-5,
    )


def test_chunks_do_not_change_the_result():
    poses = torch.stack([pose((0, 1, 0), 0.1 * i, (0.1 * i, 0, 0)) for i in range(5)]).float()
    depth = torch.stack([render_plane((0.1, 0.0, 1.0), 2.0, p.double()) for p in poses])
    frames = DepthFrames(depth, K, poses)
    a, b = depth_to_cloud(frames, stride=2, chunk=1), depth_to_cloud(frames, stride=2, chunk=8)
    assert torch.equal(a.points, b.points) and torch.equal(a.normals, b.normals)


def test_bad_arguments():
    frames = DepthFrames(torch.zeros(1, 48, 64), K, torch.eye(4))
    with pytest.raises(InputError, match="no valid pixel"):
        depth_to_cloud(frames)
    with pytest.raises(InputError, match="stride"):
        depth_to_cloud(frames, stride=0)
