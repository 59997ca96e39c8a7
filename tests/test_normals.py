"""Normal estimation and orientation (geometry.estimate_normals / orient_normals) against Open3D,
analytic surfaces and a naive tree traversal."""

import numpy as np
import pytest
import torch

from neuralsurf.errors import ConfigError, InputError, NeuralsurfError
from neuralsurf.geometry import (
    _mst_flips,
    cloud_from_mesh,
    estimate_normals,
    orient_normals,
    project_to_quadrics,
)
from neuralsurf.structures import PointCloud

CENTER = torch.tensor([5.0, -3.0, 1.0], dtype=torch.float64)


def sphere_points(n=4000, radius=2.0, seed=0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return (
        torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=torch.float64), dim=1) * radius
        + CENTER
    )


@pytest.fixture(scope="module")
def bunny_cloud() -> PointCloud:
    from neuralsurf.scenes import bunny

    return cloud_from_mesh(bunny(), 10_000, seed=3)


# ----------------------------------------------------------------------------- estimation


@pytest.mark.parametrize("k, radius", [(30, None), (30, 0.03), (None, 0.03)])
def test_matches_open3d_up_to_sign(bunny_cloud, k, radius):
    import open3d as o3d

    cloud = PointCloud(bunny_cloud.points).to_open3d()
    if radius is None:
        search = o3d.geometry.KDTreeSearchParamKNN(k)
    elif k is None:
        search = o3d.geometry.KDTreeSearchParamRadius(radius)
    else:
        search = o3d.geometry.KDTreeSearchParamHybrid(radius, k)
    cloud.estimate_normals(search)
    ours = estimate_normals(bunny_cloud.points, k=k, radius=radius).numpy()
    cos = np.abs((ours * np.asarray(cloud.normals)).sum(1))
    assert np.median(cos) > 0.99
    assert (cos > 0.99).mean() > 0.98  # the rest: near-isotropic neighbourhoods where PCA is ill-posed


def test_plane_normals_exact_and_dtype_kept():
    g = torch.Generator().manual_seed(0)
    uv = torch.rand(500, 2, generator=g, dtype=torch.float64)
    normal = torch.nn.functional.normalize(torch.tensor([1.0, 2.0, -2.0], dtype=torch.float64), dim=0)
    basis = torch.linalg.svd(normal[None]).Vh[1:]  # two unit vectors orthogonal to the normal
    points = (uv @ basis + 100.0).float()  # far from the origin, float32
    normals = estimate_normals(points, k=12)
    assert normals.dtype == torch.float32 and normals.shape == (500, 3)
    assert (normals.double() @ normal).abs().min() > 1 - 1e-5


def test_radius_too_small_warns_and_falls_back_to_three_neighbours():
    points = torch.cat([sphere_points(500), torch.tensor([[50.0, 0, 0], [60.0, 0, 0]], dtype=torch.float64)])
    with pytest.warns(UserWarning, match="fewer than 3 neighbours"):
        normals = estimate_normals(points, k=20, radius=0.5)
    assert torch.allclose(normals.norm(dim=1), torch.ones(len(points), dtype=torch.float64))


def test_point_cloud_in_point_cloud_out(bunny_cloud):
    cloud = PointCloud(bunny_cloud.points, colors=torch.zeros(len(bunny_cloud), 3))
    result = estimate_normals(cloud, k=30, orient="mst")
    assert isinstance(result, PointCloud) and result.has_normals
    assert torch.equal(result.points, cloud.points) and result.colors is not None
    assert ((result.normals * bunny_cloud.normals).sum(1) > 0).double().mean() > 0.99


# ----------------------------------------------------------------------------- orientation


def test_mst_orients_sphere_outward():
    points = sphere_points()
    normals = estimate_normals(points, k=20, orient="mst")
    assert ((normals * (points - CENTER)).sum(1) > 0).double().mean() > 0.99


def test_mst_orients_bunny_outward(bunny_cloud):
    scrambled = estimate_normals(bunny_cloud.points, k=30)  # arbitrary signs
    oriented = orient_normals(bunny_cloud.points, scrambled, 30)
    assert ((oriented * bunny_cloud.normals).sum(1) > 0).double().mean() > 0.99
    assert torch.equal(oriented.abs(), scrambled.abs())  # only signs change


def naive_mst_flips(coords: np.ndarray, normals: np.ndarray, k: int) -> np.ndarray:
    """Reference: the tree traversal written out node by node (Hoppe et al. 1992)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import breadth_first_order, minimum_spanning_tree
    from scipy.spatial import cKDTree

    n = len(coords)
    _, index = cKDTree(coords).query(coords, k + 1)
    rows, cols = np.repeat(np.arange(n), k), index[:, 1:].reshape(-1)
    weights = 1.0 - np.abs((normals[rows] * normals[cols]).sum(-1)) + 1e-9
    graph = coo_matrix((weights, (rows, cols)), shape=(n, n)).tocsr()
    tree = minimum_spanning_tree(graph.maximum(graph.T))
    tree = tree.maximum(tree.T)
    oriented, visited = normals.copy(), np.zeros(n, dtype=bool)
    while not visited.all():
        root = int(np.flatnonzero(~visited)[np.argmax(coords[~visited, 0])])
        if oriented[root, 0] < 0:
            oriented[root] *= -1
        order, parents = breadth_first_order(tree, root, directed=False)
        for node in order[1:]:
            if oriented[node] @ oriented[parents[node]] < 0:
                oriented[node] *= -1
        visited[order] = True
    return (oriented * normals).sum(1) < 0


def test_mst_pointer_jumping_matches_naive_traversal():
    rng = np.random.default_rng(0)
    # two separate blobs: two components, each with its own root
    coords = np.concatenate([rng.normal(size=(300, 3)), rng.normal(size=(200, 3)) + 100])
    normals = rng.normal(size=(500, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    np.testing.assert_array_equal(_mst_flips(coords, normals, 8), naive_mst_flips(coords, normals, 8))


def test_camera_orientation_single_and_per_point():
    points = sphere_points(2000)
    inward = estimate_normals(points, k=20, orient="camera", camera=CENTER)
    assert ((inward * (points - CENTER)).sum(1) < 0).all()
    outside = points + 3 * (points - CENTER)  # one sensor per point, outside the sphere
    outward = estimate_normals(points, k=20, orient="camera", camera=outside)
    assert ((outward * (points - CENTER)).sum(1) > 0).all()


def test_direction_orientation():
    points = sphere_points(2000)
    direction = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)
    normals = estimate_normals(points, k=20, orient="direction", direction=direction)
    assert (normals @ direction >= 0).all()


def test_float32_normals_estimated_then_oriented_all_face_outward():
    """estimate_normals(points, k) then orient_normals(points, normals, k), as a point fit prepares a cloud.

    float32 on purpose: rounding gave |cos| > 1, negative MST weights and 1.5 % flipped normals."""
    points = sphere_points(1000).float()
    normals = orient_normals(points, estimate_normals(points, 20), 20)
    assert normals.dtype == torch.float32
    assert ((normals.double() * (points.double() - CENTER)).sum(1) > 0).all()


# ----------------------------------------------------------------------------- bad input


@pytest.mark.parametrize(
    "kwargs, error, match",
    [
        ({"orient": "towards"}, ConfigError, "unknown normal orientation"),
        ({"orient": "camera"}, ConfigError, "needs camera"),
        ({"camera": CENTER}, ConfigError, "only used with orient='camera'"),
        ({"orient": "direction"}, ConfigError, "needs direction"),
        ({"k": 2}, ConfigError, "k >= 3"),
        ({"k": None}, ConfigError, "needs k, radius or both"),
        ({"radius": -1.0}, ConfigError, "radius must be > 0"),
        ({"orient": "camera", "camera": torch.zeros(5, 3)}, InputError, r"shape \(3,\) or \(100, 3\)"),
    ],
)
def test_bad_arguments_raise_clear_errors(kwargs, error, match):
    with pytest.raises(error, match=match):
        estimate_normals(sphere_points(100), **kwargs)


def test_too_few_points_or_bad_shape():
    with pytest.raises(NeuralsurfError, match="at least 3 points"):
        estimate_normals(torch.zeros(2, 3))
    with pytest.raises(NeuralsurfError, match=r"shape \(n, 3\)"):
        estimate_normals(torch.zeros(10, 2))


def test_projection_onto_local_quadrics_removes_noise_across_a_sphere_without_shrinking_it():
    """Oracle: the sphere's radius. 20k points with Gaussian noise 1% of the radius: after one
    projection the radial error is less than half, its mean stays about 0 (a plane would pull the
    points inwards by about r_k^2 / 2R), and the points move along their normals only."""
    clean = sphere_points(20_000)
    g = torch.Generator().manual_seed(1)
    noisy = clean + 0.02 * torch.randn(clean.shape, generator=g, dtype=torch.float64)
    normals = estimate_normals(noisy, k=30)
    projected = project_to_quadrics(noisy, normals, k=30)
    radial = lambda p: (p - CENTER).norm(dim=1) - 2.0
    assert radial(projected).abs().mean() < radial(noisy).abs().mean() / 2.5
    assert radial(projected).mean().abs() < 0.002
    tangential = projected - noisy - ((projected - noisy) * normals).sum(-1, keepdim=True) * normals
    assert tangential.abs().max() < 1e-12
    with pytest.raises(ConfigError, match="6 <= k"):
        project_to_quadrics(noisy, normals, k=5)
