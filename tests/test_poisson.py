"""Screened Poisson reconstruction (baselines.poisson): analytic sphere, density trimming, real scans."""

import numpy as np
import pytest
import torch

from neuralsurf.baselines.poisson import reconstruct_poisson, trim_low_density
from neuralsurf.errors import ConfigError, InputError
from neuralsurf.geometry import point_to_mesh_distance, sample_mesh_surface
from neuralsurf.structures import Mesh, PointCloud

CENTER = torch.tensor([10.0, -5.0, 3.0], dtype=torch.float64)
RADIUS = 2.0


def sphere_cloud(n=20_000, normals=True, hemisphere=False, seed=0) -> PointCloud:
    g = torch.Generator().manual_seed(seed)
    unit = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=torch.float64), dim=1)
    if hemisphere:
        unit = unit[unit[:, 2] > 0]
    return PointCloud(CENTER + RADIUS * unit, unit if normals else None)


def radial_error(mesh: Mesh) -> torch.Tensor:
    """Float[Tensor, "v"]: | |v - c| - r | of every vertex, in the world frame."""
    return ((mesh.vertices.double() - CENTER).norm(dim=1) - RADIUS).abs()


def test_sphere_in_world_frame():
    mesh = reconstruct_poisson(sphere_cloud(), depth=7)
    assert mesh.vertices.dtype == torch.float64 and mesh.is_watertight
    error = radial_error(mesh)
    assert error.mean() < 0.005 * RADIUS and error.max() < 0.02 * RADIUS
    assert torch.allclose(mesh.vertices.mean(0), CENTER, atol=0.01)  # lies on its input, not in a unit cube


def test_a_cloud_far_from_the_origin_is_solved_as_at_the_origin():
    """Open3D's solver rounds to float32, which at a georeferenced origin (0.25 there) would miss a 2 m sphere."""
    far = torch.tensor([412_345.0, 5_012_345.0, 100.0], dtype=torch.float64)
    cloud = sphere_cloud()
    expected = reconstruct_poisson(cloud, depth=7, n_threads=1)
    mesh = reconstruct_poisson(PointCloud(cloud.points + far, cloud.normals), depth=7, n_threads=1)
    assert len(mesh.faces) == pytest.approx(len(expected.faces), rel=0.01)
    error = ((mesh.vertices - far - CENTER).norm(dim=1) - RADIUS).abs()
    assert error.mean() < 0.005 * RADIUS and error.max() < 0.02 * RADIUS


def test_density_trim_removes_the_hallucinated_cap():
    """An open hemisphere: Poisson closes it with a low-density cap far from the data; trimming
    the lowest densities removes vertices there first."""
    cloud = sphere_cloud(hemisphere=True)
    full = reconstruct_poisson(cloud, depth=7)
    trimmed = reconstruct_poisson(cloud, depth=7, density_trim=0.1)
    assert 0.85 * len(full.vertices) < len(trimmed.vertices) < 0.95 * len(full.vertices)
    far = lambda mesh: (radial_error(mesh) > 0.05 * RADIUS).double().mean()
    assert far(trimmed) < far(full) / 2
    assert int(trimmed.faces.max()) < len(trimmed.vertices)


def test_missing_normals_are_estimated_with_a_warning():
    with pytest.warns(UserWarning, match="no normals; estimating"):
        mesh = reconstruct_poisson(sphere_cloud(normals=False), depth=6)
    assert radial_error(mesh).mean() < 0.01 * RADIUS  # a wrong orientation would give no sphere
    with pytest.raises(InputError, match="needs oriented normals.*estimate_normals=False"):
        reconstruct_poisson(sphere_cloud(normals=False), estimate_normals=False)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"depth": 0}, "depth must lie in 1..16"),
        ({"scale": 0.5}, "scale must be >= 1"),
        ({"density_trim": 1.0}, r"quantile in \[0, 1\)"),
    ],
)
def test_bad_arguments(kwargs, match):
    with pytest.raises(ConfigError, match=match):
        reconstruct_poisson(sphere_cloud(100), **kwargs)


def test_trim_low_density_reindexes_faces():
    vertices = torch.tensor([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [2, 2, 0]], dtype=torch.float64)
    faces = torch.tensor([[0, 1, 2], [1, 3, 2], [3, 4, 2]])
    mesh = trim_low_density(Mesh(vertices, faces), np.array([5.0, 1.0, 5.0, 5.0, 5.0]), 0.2)
    # vertex 1 (density 1, below the 20 % quantile) goes, with the two faces that use it
    assert torch.equal(mesh.vertices, vertices[[2, 3, 4]])
    assert mesh.faces.tolist() == [[1, 2, 0]]


@pytest.mark.slow
def test_real_scans_merged_match_the_zipper_mesh(shared_data):
    """The ten Stanford bunny scans at their .conf poses, merged and reconstructed (depth 9): exact
    distances to bun_zipper.ply below 1 mm each way (zipper is open at the base; Poisson closes it)."""
    from neuralsurf.io import read_mesh, read_range_scans

    scans = read_range_scans(shared_data / "stanford_bunny" / "data" / "bun.conf")
    merged = PointCloud(
        torch.cat([s.points.double() for s in scans]), torch.cat([s.normals.double() for s in scans])
    )
    mesh = reconstruct_poisson(merged, depth=9)
    gt = read_mesh(shared_data / "stanford_bunny" / "reconstruction" / "bun_zipper.ply")
    g = torch.Generator().manual_seed(0)
    accuracy = point_to_mesh_distance(sample_mesh_surface(mesh, 100_000, g)[0].double(), gt).double().mean()
    completeness = (
        point_to_mesh_distance(sample_mesh_surface(gt, 100_000, g)[0].double(), mesh).double().mean()
    )
    assert accuracy < 1e-3 and completeness < 1e-3
    assert 0.5 * (accuracy + completeness) < 0.5e-3


@pytest.mark.parametrize("n", [3, 4, 31])
def test_too_few_points_are_refused(n):
    with pytest.raises(InputError, match=f"needs at least 32 points, got {n}"):
        reconstruct_poisson(sphere_cloud(n), depth=6)


def _flat_cloud(shape: str, n: int = 500) -> PointCloud:
    g = torch.Generator().manual_seed(0)
    t = torch.rand(n, 2, generator=g, dtype=torch.float64)
    if shape == "line":
        points = CENTER + t[:, :1] * torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    else:  # a tilted plane through CENTER
        points = CENTER + t[:, :1] * torch.tensor([1.0, 0.0, 1.0], dtype=torch.float64) + t[:, 1:] * torch.tensor(
            [0.0, 1.0, 0.0], dtype=torch.float64
        )
    normal = torch.tensor([1.0, 0.0, -1.0], dtype=torch.float64) / 2**0.5
    return PointCloud(points.float(), normal.expand(n, 3).float())  # float32, as clouds read from files are


@pytest.mark.parametrize("shape, match", [("line", "lie on a line"), ("plane", "lie in a plane")])
def test_degenerate_clouds_are_refused(shape, match):
    with pytest.raises(InputError, match=f"Poisson reconstruction: the 500 points {match}.*zero-thickness"):
        reconstruct_poisson(_flat_cloud(shape), depth=6)


def test_identical_points_are_refused():
    cloud = PointCloud(CENTER.expand(100, 3), torch.tensor([0.0, 0.0, 1.0]).expand(100, 3))
    with pytest.raises(InputError, match="all 100 points lie at one location"):
        reconstruct_poisson(cloud, depth=6)


def test_a_thin_but_solid_slab_is_accepted():
    """The check refuses exact degeneracy only: a box 1000 times thinner than wide still has a volume."""
    cloud = _flat_cloud("plane")
    offset = torch.zeros(len(cloud), 3)
    offset[::2] = torch.tensor([1e-3, 0.0, -1e-3])  # along the plane's normal
    mesh = reconstruct_poisson(PointCloud(cloud.points + offset, cloud.normals), depth=6)
    assert len(mesh.faces) > 0
