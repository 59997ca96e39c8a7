"""A mesh moved onto the points it was fitted to (neuralsurf.snapping): against an analytic sphere, Open3D's
point-to-mesh distance and exact planes."""

from __future__ import annotations

import logging

import pytest
import torch

from neuralsurf.errors import ConfigError
from neuralsurf.extract import extract_mesh
from neuralsurf.geometry import point_to_mesh_distance, sample_mesh_surface
from neuralsurf.sampling import held_out_split
from neuralsurf.scenes.analytic import Sphere
from neuralsurf.snapping import (
    footprints,
    plane_offsets,
    ring_mean,
    snap_to_cloud,
    snap_to_points,
    subdivided,
)
from neuralsurf.structures import Mesh, PointCloud

BOX = torch.tensor([[-0.5] * 3, [0.5] * 3], dtype=torch.float64)
SPHERE = Sphere(center=(0.02, -0.01, 0.03))


def off_sphere(mesh: Mesh) -> float:
    """The mean distance of the mesh's surface to the sphere."""
    samples, _ = sample_mesh_surface(mesh, 50_000, torch.Generator().manual_seed(1))
    return float(SPHERE.sdf(samples.double()).abs().mean())


@pytest.fixture(scope="module")
def coarse() -> Mesh:
    """The sphere marched at 24 cells: its faces cut inside the sphere (chords)."""
    return extract_mesh(SPHERE.sdf, 24, BOX, progress=False)


def test_a_subdivided_mesh_is_the_same_surface_with_each_face_s_children_in_its_place(coarse):
    colored = Mesh(coarse.vertices, coarse.faces, torch.rand(len(coarse.vertices), 3))
    fine = subdivided(colored)
    assert len(fine.faces) == 4 * len(coarse.faces) and fine.is_watertight
    assert float(fine.face_areas().double().sum()) == pytest.approx(float(coarse.face_areas().double().sum()), rel=1e-6)
    count = len(coarse.faces)
    corners = coarse.vertices[coarse.faces]
    center = corners.mean(1)
    for j in range(4):  # child j of face i is face i + j * count: the corner children halfway to their corner
        centroid = fine.vertices[fine.faces[torch.arange(count) + j * count]].mean(1)
        assert torch.allclose(centroid, (center + corners[:, j]) / 2 if j < 3 else center, atol=1e-6)
    middle = fine.faces[3 * count]  # the middle child's corners are the first face's edge midpoints
    a, b = coarse.faces[0, :2]
    assert torch.allclose(fine.vertex_colors[middle[0]], (colored.vertex_colors[a] + colored.vertex_colors[b]) / 2)


def test_plane_offsets_are_the_heights_above_a_plane_of_points():
    grid = torch.stack(torch.meshgrid(torch.linspace(-1, 1, 41), torch.linspace(-1, 1, 41), indexing="ij"), -1)
    points = torch.cat([grid.reshape(-1, 2), torch.zeros(41 * 41, 1)], -1)
    normals = torch.tensor([0.0, 0, 1]).expand_as(points)
    vertices = torch.tensor([[0.01, 0.02, 0.03], [-0.3, 0.4, -0.02], [0.2, 0.1, 0.5]])
    offset, direction = plane_offsets(vertices, points, normals, spacing=0.05)
    assert torch.allclose(offset, torch.tensor([0.03, -0.02, 0.0]), atol=1e-6)  # the last: beyond two spacings
    assert torch.allclose(direction, normals[:3])


def test_ring_mean_keeps_a_constant_and_averages_a_vertex_with_its_neighbours(coarse):
    incident = coarse.faces.reshape(-1).bincount(minlength=len(coarse.vertices))
    assert torch.allclose(ring_mean(torch.full((len(coarse.vertices),), 2.0), coarse.faces, incident),
                          torch.tensor(2.0))
    spike = torch.zeros(len(coarse.vertices))
    spike[0] = 1.0
    spread = ring_mean(spike, coarse.faces, incident)
    ring = coarse.faces[(coarse.faces == 0).any(1)].unique()
    assert 0 < float(spread[0]) < 1 and (spread[ring] > 0).all() and float(spread.sum()) == pytest.approx(1.0, rel=0.3)


def test_exact_points_bring_a_coarse_mesh_onto_the_sphere(coarse):
    cloud = SPHERE.sample_surface(40_000, seed=0)
    held, kept = held_out_split(len(cloud), 0.05, seed=0)
    snapped, measured = snap_to_points(coarse, cloud.points[kept], cloud.normals[kept], cloud.points[held])
    assert measured["rounds"] == 0 and measured["held_out_after"] < 0.3 * measured["held_out_before"]
    assert snapped.is_watertight and len(snapped.faces) == 4 * len(coarse.faces)
    assert off_sphere(snapped) < 0.3 * off_sphere(coarse)


@pytest.mark.parametrize("resolution, moved", [(24, True), (64, False)])
def test_noisy_points_move_a_mesh_smoothly_or_not_at_all(resolution, moved):
    """Points scattered 0.004 off the sphere: against a coarse mesh's chords (up to 0.009) the held-out points ask
    for a smooth move, against a fine one's (0.0013) for none; the mesh never comes out farther from the sphere."""
    mesh = extract_mesh(SPHERE.sdf, resolution, BOX, progress=False)
    cloud = SPHERE.sample_surface(60_000, seed=0)
    noisy = cloud.points + 0.004 * torch.randn(cloud.points.shape, generator=torch.Generator().manual_seed(2))
    held, kept = held_out_split(len(noisy), 0.05, seed=0)
    snapped, measured = snap_to_points(mesh, noisy[kept], cloud.normals[kept], noisy[held])
    assert (measured["rounds"] >= 8) if moved else (measured["rounds"] == -1 and snapped is mesh)
    assert off_sphere(snapped) <= (0.7 if moved else 1.0) * off_sphere(mesh)


def test_snap_to_cloud_leaves_a_mesh_where_the_points_hold_nothing_more(coarse, caplog):
    dense = SPHERE.sample_surface(40_000, seed=0)
    with caplog.at_level(logging.INFO, logger="neuralsurf"):
        assert snap_to_cloud(coarse, PointCloud(dense.points), 0.05) is coarse
        assert snap_to_cloud(coarse, SPHERE.sample_surface(100, seed=0), 0.05) is coarse  # sparser than the mesh
    assert "no normals" in caplog.text and "no closer together" in caplog.text
    assert len(snap_to_cloud(coarse, dense, 0.05).faces) == 4 * len(coarse.faces)
    for share in (0.0, 0.5, -0.1):
        with pytest.raises(ConfigError, match="onto_points"):
            snap_to_cloud(coarse, dense, share)


def test_a_cloud_far_from_the_origin_moves_its_mesh_as_at_the_origin(coarse):
    """Georeferenced coordinates (float32 rounds them by up to 0.25) move the mesh as the same cloud at the origin."""
    far = torch.tensor([412_345.0, 5_012_345.0, 100.0], dtype=torch.float64)
    dense = SPHERE.sample_surface(40_000, seed=0)
    expected = snap_to_cloud(coarse, dense, 0.05)
    moved = snap_to_cloud(Mesh(coarse.vertices.double() + far, coarse.faces), PointCloud(dense.points + far,
                                                                                           dense.normals), 0.05)
    assert moved.vertices.dtype == torch.float64 and torch.equal(moved.faces, expected.faces)
    assert torch.allclose(moved.vertices - far, expected.vertices.double(), atol=1e-5)


def test_the_held_out_split_is_fixed_by_its_seed_and_disjoint():
    held, kept = held_out_split(1000, 0.05, seed=3)
    assert len(held) == 50 and len(kept) == 950
    assert torch.equal(torch.cat([held, kept]).sort().values, torch.arange(1000))
    assert torch.equal(held, held_out_split(1000, 0.05, seed=3)[0])
    assert not torch.equal(held, held_out_split(1000, 0.05, seed=4)[0])


def test_a_footprint_s_height_is_the_distance_to_the_mesh(coarse):
    query = SPHERE.sample_surface(2000, seed=5).points.float()
    under, weights, normal = footprints(query, coarse)
    fine = subdivided(coarse)
    surface = (weights[..., None] * fine.vertices[fine.faces[under]]).sum(1)
    assert float(point_to_mesh_distance(surface, coarse).max()) < 1e-6 and float(weights.min()) >= 0
    height = ((query - surface) * normal).sum(-1).abs()
    assert torch.allclose(height, point_to_mesh_distance(query, coarse), atol=1e-5)


def test_plane_offsets_read_in_chunks_are_the_same(coarse, monkeypatch):
    cloud = SPHERE.sample_surface(5_000, seed=0)
    whole = plane_offsets(coarse.vertices, cloud.points, cloud.normals, spacing=0.01)
    monkeypatch.setattr("neuralsurf.snapping.CHUNK", 100)
    chunked = plane_offsets(coarse.vertices, cloud.points, cloud.normals, spacing=0.01)
    assert torch.equal(whole[0], chunked[0]) and torch.equal(whole[1], chunked[1])


def test_a_coloured_cloud_colours_its_mesh_and_a_plain_one_leaves_it_plain():
    """Oracle: colours that are a linear function of position; the mesh's vertices take them from the points."""
    from neuralsurf.scenes import Scene
    from neuralsurf.scenes.recipes import extract_scene_mesh

    cloud = SPHERE.sample_surface(40_000, seed=0)
    colour_at = lambda x: (x.double() - torch.tensor(SPHERE.center)) / (2 * SPHERE.radius) + 0.5
    coloured = PointCloud(cloud.points, cloud.normals, colour_at(cloud.points))
    mesh = extract_scene_mesh(SPHERE.sdf, Scene("ball", coloured, None), {"resolution": 48, "bounds": BOX,
                                                                        "progress": False})
    assert mesh.vertex_colors is not None
    assert (mesh.vertex_colors.double() - colour_at(mesh.vertices)).abs().max() < 0.02
    plain = extract_scene_mesh(SPHERE.sdf, Scene("ball", cloud, None), {"resolution": 48, "bounds": BOX,
                                                                       "progress": False})
    assert plain.vertex_colors is None and torch.equal(plain.vertices, mesh.vertices)
