"""Observed space of depth frames (neuralsurf.observations.observed) against analytic scenes: a plane seen
by cameras facing it, a patch of readings that the other views see through, and a plane field whose mesh is
kept only where the frames saw the plane."""

from __future__ import annotations

import pytest
import torch

from neuralsurf.cameras import depth_rays, stride_frames, strided_hits
from neuralsurf.observations.observed import ObservedSurface, extract_observed, view_votes
from neuralsurf.structures import DepthFrames, Mesh

WIDTH, HEIGHT, F = 64, 48, 60.0
PLANE_Z = 2.0


def plane_frames(xs=(-0.2, 0.0, 0.2), width=WIDTH) -> DepthFrames:
    """Cameras at (x, 0, 0) looking along +z (identity rotation) at the plane z = 2: depth 2 everywhere."""
    n = len(xs)
    K = torch.tensor([[F, 0, (width - 1) / 2], [0, F, (HEIGHT - 1) / 2], [0, 0, 1]]).expand(n, 3, 3).clone()
    pose = torch.eye(4).repeat(n, 1, 1)
    pose[:, 0, 3] = torch.tensor(xs)
    return DepthFrames(torch.full((n, HEIGHT, width), PLANE_Z), K, pose)


def test_stride_frames_keeps_the_rays_of_the_kept_pixels():
    frames = plane_frames()
    frames.depth[:, 10:20, 5:30] = 1.5  # a step, so the rays differ between pixels
    full = depth_rays(frames)
    strided = depth_rays(stride_frames(frames, 3))
    keep = torch.zeros(frames.depth.shape, dtype=torch.bool)
    keep[:, ::3, ::3] = True
    index = keep.flatten().nonzero()[:, 0]
    assert torch.allclose(strided.directions, full.directions[index], atol=1e-6)
    assert torch.allclose(strided.hit, full.hit[index], atol=1e-6)
    assert torch.equal(strided.origins, full.origins[index])


def test_strided_hits_lie_on_the_plane_and_thin_out():
    frames = plane_frames()
    points = strided_hits(frames, 2)
    assert len(points) == 3 * (HEIGHT // 2) * (WIDTH // 2)
    assert torch.allclose(points[:, 2], torch.full((len(points),), PLANE_Z, dtype=torch.float64))


def test_view_votes_near_free_and_unseen():
    frames = plane_frames()
    points = torch.tensor([[0.0, 0.0, PLANE_Z], [0.0, 0.0, 1.0], [0.0, 0.0, 3.0], [50.0, 0.0, 2.0]], dtype=torch.float64)
    near, free = view_votes(points, frames, band=0.05)
    assert near.tolist() == [3, 0, 0, 0]  # on the plane; in front; behind; outside every image
    assert free.tolist() == [0, 3, 0, 0]


def test_observed_voxels_hold_readings_and_their_neighbours_not_seen_through():
    frames = plane_frames()
    voxel = 0.05
    observed = ObservedSurface.from_frames(frames, voxel, band=0.01, min_hits=1, pixel_stride=1)
    plane_point = strided_hits(frames, 1)[:1]
    assert observed.contains(plane_point).item()
    centres = observed.origin + (observed.mask.nonzero().double() + 0.5) * voxel
    # the plane's voxels and those behind it, none in the free space the cameras saw in front of it
    assert centres[:, 2].min() >= PLANE_Z - voxel and centres[:, 2].max() <= PLANE_Z + 2 * voxel
    assert (centres[:, 2] > PLANE_Z + 0.5 * voxel).any()
    trusting = ObservedSurface.from_frames(frames, voxel, band=0.01, min_hits=1, pixel_stride=1, max_free_ratio=None)
    assert (trusting.mask & ~observed.mask).any()  # without the votes, the neighbours in front are kept
    in_front = torch.tensor([[0.0, 0.0, 1.5]], dtype=torch.float64)
    assert not observed.contains(in_front).item() and not trusting.contains(in_front).item()


def test_extraction_keeps_only_the_seen_part_of_a_plane():
    frames = plane_frames()
    observed = ObservedSurface.from_frames(frames, 0.05, pixel_stride=2)

    def field(x):  # z = 2 plane, negative behind it, and a second plane z = 1.2 no frame saw
        return torch.minimum(PLANE_Z - x[..., 2], (x[..., 2] - 1.2).abs() - 0.01 + 0 * x[..., 0])

    mesh = extract_observed(field, observed, resolution=64)  # no vertex of the unseen plane z = 1.2
    assert (mesh.vertices[:, 2] - PLANE_Z).abs().max() < 0.01
    hits = strided_hits(frames, 2)
    lo, hi = hits.min(0).values, hits.max(0).values
    reach = 2 * 0.05  # at most the observed voxels' unseen neighbours beyond the last reading
    assert (mesh.vertices[:, :2].double() >= lo[:2] - reach).all() and (mesh.vertices[:, :2].double() <= hi[:2] + reach).all()
    # the crop keeps the faces in observed voxels: the mesh covers the seen part of the plane
    area = torch.linalg.cross(*(mesh.vertices[mesh.faces[:, i]] - mesh.vertices[mesh.faces[:, 0]] for i in (1, 2))).norm(dim=-1).sum() / 2
    seen = float((hi[0] - lo[0]) * (hi[1] - lo[1]))
    assert 0.8 * seen < area < 1.3 * seen


def test_crop_removes_faces_outside_and_names_an_empty_result():
    observed = ObservedSurface(torch.zeros(3, dtype=torch.float64), 1.0, torch.zeros(2, 2, 2, dtype=torch.bool))
    observed.mask[0, 0, 0] = True
    mesh = Mesh(torch.tensor([[0.1, 0.1, 0.5], [0.9, 0.1, 0.5], [0.1, 0.9, 0.5], [1.5, 1.5, 0.5], [1.9, 1.5, 0.5],
                              [1.5, 1.9, 0.5]]), torch.tensor([[0, 1, 2], [3, 4, 5]]))
    cropped = observed.crop(mesh)
    assert cropped.faces.tolist() == [[0, 1, 2]] and len(cropped.vertices) == 3
    empty = ObservedSurface(torch.zeros(3, dtype=torch.float64), 1.0, torch.zeros(2, 2, 2, dtype=torch.bool))
    with pytest.raises(Exception, match="no face of the mesh lies in an observed voxel"):
        empty.crop(mesh)


def test_bad_settings_are_named():
    with pytest.raises(Exception, match="voxel > 0"):
        ObservedSurface.from_frames(plane_frames(), 0.0)
    frames = plane_frames()
    frames.depth.zero_()
    with pytest.raises(Exception, match="missing"):
        ObservedSurface.from_frames(frames, 0.05)


def test_depth_rays_pixel_stride_fits_the_strided_pixels_and_names_a_bad_stride():
    from neuralsurf.errors import ConfigError
    from neuralsurf.observations import DepthRays

    frames = plane_frames()
    rays = DepthRays(frames, pixel_stride=2).world_rays
    assert len(rays.hit) == 3 * (HEIGHT // 2) * (WIDTH // 2)
    with pytest.raises(ConfigError, match="pixel_stride"):
        DepthRays(frames, pixel_stride=0)


def test_observed_points_lie_in_observed_voxels_and_feed_the_carve_pool():
    from neuralsurf.observations import DepthRays
    from neuralsurf.observations.observed import observed_points
    from neuralsurf.structures import Normalization

    frames = plane_frames()
    observed = ObservedSurface.from_frames(frames, 0.05, max_free_ratio=None)
    points = observed_points(observed, 500, torch.Generator().manual_seed(0))
    assert observed.contains(points, grown=True).all()
    observation = DepthRays(frames, carve_voxel=0.05, n_carve=400, winding_points=0, denoise_k=0)
    normalization = Normalization.from_points(observation.bounds())
    sampler = observation.prepare(normalization, 0.55, torch.device("cpu"), 0)
    pool = normalization.to_world(sampler.carved[0].double())
    near_plane = (pool[:, 2] - PLANE_Z).abs() < 0.15
    assert near_plane[:200].all() and near_plane.float().mean() < 0.9  # half near the surface, half in the box


def test_extract_scene_mesh_meshes_a_room_where_its_frames_saw_a_surface():
    from neuralsurf.scenes import extract_scene_mesh
    from neuralsurf.scenes.recipes import depth_scene

    scene = depth_scene("plane", plane_frames(), cloud_stride=4, near_distance=0.05)

    def field(x):  # the seen plane z = 2 and an unseen one at z = 1.2
        return torch.minimum(PLANE_Z - x[..., 2], (x[..., 2] - 1.2).abs() - 0.01)

    mesh = extract_scene_mesh(field, scene, {"resolution": 64, "observed_voxel": 0.05, "format": "ply"})
    assert (mesh.vertices[:, 2] - PLANE_Z).abs().max() < 0.01
