"""Pure geometric operations on tensors: neighbours, normals, mesh sampling and distances.

Inputs and outputs are tensors in the caller's frame; nothing here normalises or learns.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from neuralsurf.errors import InputError
from neuralsurf.structures import Mesh, PointCloud


def knn(query: Tensor, points: Tensor, k: int = 1) -> tuple[Tensor, Tensor]:
    """Exact k nearest neighbours of each query among `points` (k-d tree, all cores).

    Args:
        query: Float[Tensor, "m 3"].
        points: Float[Tensor, "n 3"].
        k: neighbours per query, 1 <= k <= n.
    Returns:
        distances Float[Tensor, "m k"] (query dtype) and indices Int[Tensor, "m k"] (int64).
    """
    from scipy.spatial import cKDTree

    if not 1 <= k <= len(points):
        raise InputError(f"knn needs 1 <= k <= {len(points)} (number of points), got k={k}")
    tree = cKDTree(points.detach().cpu().double().numpy())
    dist, index = tree.query(query.detach().cpu().double().numpy(), k=k, workers=-1)
    dist, index = np.asarray(dist).reshape(len(query), k), np.asarray(index).reshape(len(query), k)
    return (
        torch.from_numpy(dist).to(query.dtype).to(query.device),
        torch.from_numpy(index).long().to(query.device),
    )


def estimate_normals(points: Tensor, k: int = 30) -> Tensor:
    """Unoriented unit normals by PCA of the k nearest neighbours.

    Args:
        points: Float[Tensor, "n 3"] with n >= 3.
    Returns:
        Float[Tensor, "n 3"]: the direction of least variance of each neighbourhood (sign arbitrary).
    """
    if len(points) < 3:
        raise InputError(f"normal estimation needs at least 3 points, got {len(points)}")
    _, index = knn(points, points, min(k, len(points)))
    neighbours = points[index].double()  # (n, k, 3)
    centred = neighbours - neighbours.mean(1, keepdim=True)
    covariance = centred.transpose(1, 2) @ centred  # (n, 3, 3)
    _, eigenvectors = torch.linalg.eigh(covariance)
    return eigenvectors[..., 0].to(points.dtype)


def orient_normals(points: Tensor, normals: Tensor, k: int = 30) -> Tensor:
    """Flip normals consistently along a minimum spanning tree (Hoppe et al. 1992), outward.

    The tree is grown over the k-NN graph with weights 1 - |n_i . n_j|; the root is the point
    with the largest x, whose normal is made to point along +x so that the result faces outward
    for a closed surface.

    Args:
        points: Float[Tensor, "n 3"]; normals: Float[Tensor, "n 3"] unit, any signs.
    Returns:
        Float[Tensor, "n 3"]: the same normals with consistent signs.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import breadth_first_order, minimum_spanning_tree

    n = len(points)
    k = min(k, n - 1)
    _, index = knn(points, points, k + 1)
    rows = torch.arange(n).repeat_interleave(k).numpy()
    cols = index[:, 1:].reshape(-1).cpu().numpy()
    nrm = normals.detach().cpu().double().numpy()
    weights = 1.0 - np.abs((nrm[rows] * nrm[cols]).sum(-1)) + 1e-9
    graph = coo_matrix((weights, (rows, cols)), shape=(n, n))
    tree = minimum_spanning_tree(graph.maximum(graph.T)).tocsr()
    tree = tree.maximum(tree.T)
    oriented = nrm.copy()
    visited = np.zeros(n, dtype=bool)
    coords = points.detach().cpu().double().numpy()
    while not visited.all():  # one traversal per connected component
        root = int(np.flatnonzero(~visited)[np.argmax(coords[~visited, 0])])
        if oriented[root, 0] < 0:
            oriented[root] *= -1
        order, parents = breadth_first_order(tree, root, directed=False)
        for node in order[1:]:
            if np.dot(oriented[node], oriented[parents[node]]) < 0:
                oriented[node] *= -1
        visited[order] = True
    return torch.from_numpy(oriented).to(normals)


def sample_mesh_surface(mesh: Mesh, n: int, generator: torch.Generator | None = None) -> tuple[Tensor, Tensor]:
    """Uniform random points on a mesh's surface (area-weighted), with the face normals there.

    Returns:
        points Float[Tensor, "n 3"] and normals Float[Tensor, "n 3"], in the mesh's dtype.
    """
    if mesh.is_empty:
        raise InputError("cannot sample the surface of an empty mesh (it has no faces)")
    vertices = mesh.vertices.detach().cpu().double()
    faces = mesh.faces.cpu()
    areas = Mesh(vertices, faces).face_areas()
    face = torch.multinomial(areas, n, replacement=True, generator=generator)
    u, v = torch.rand(2, n, 1, dtype=torch.float64, generator=generator)
    flip = (u + v) > 1  # fold the unit square onto the triangle
    u, v = torch.where(flip, 1 - u, u), torch.where(flip, 1 - v, v)
    a, b, c = vertices[faces[face]].unbind(1)
    points = a + u * (b - a) + v * (c - a)
    normals = Mesh(vertices, faces).face_normals()[face]
    return points.to(mesh.vertices), normals.to(mesh.vertices)


def _raycasting_scene(mesh: Mesh):
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(mesh.vertices.detach().cpu().float().numpy()),
        o3d.core.Tensor(mesh.faces.cpu().numpy().astype(np.uint32)),
    )
    return scene


def point_to_mesh_distance(points: Tensor, mesh: Mesh) -> Tensor:
    """Exact Euclidean distance from each point to the closest point on the mesh's triangles.

    Args:
        points: Float[Tensor, "n 3"]; mesh: non-empty Mesh in the same frame.
    Returns:
        Float[Tensor, "n"] in the points' dtype (computed in float32 by Open3D's BVH; to
        keep relative precision the mesh and points are re-centred on the mesh first).
    """
    if mesh.is_empty:
        raise InputError("point_to_mesh_distance needs a mesh with faces, got an empty mesh")
    center = mesh.vertices.double().mean(0)
    centred = Mesh(mesh.vertices.double() - center, mesh.faces)
    scene = _raycasting_scene(centred)
    import open3d as o3d

    query = (points.detach().cpu().double() - center.cpu()).float().numpy()
    distance = scene.compute_distance(o3d.core.Tensor(query)).numpy()
    return torch.from_numpy(distance).to(points)


def mesh_signed_distance(points: Tensor, mesh: Mesh) -> Tensor:
    """Float[Tensor, "n"]: signed distance to a watertight mesh, negative inside."""
    distance = point_to_mesh_distance(points, mesh)
    return torch.where(mesh_contains(points, mesh), -distance, distance)


def mesh_contains(points: Tensor, mesh: Mesh) -> Tensor:
    """Bool[Tensor, "n"]: which points lie inside a watertight mesh (majority of 3 ray parities)."""
    import open3d as o3d

    center = mesh.vertices.double().mean(0)
    scene = _raycasting_scene(Mesh(mesh.vertices.double() - center, mesh.faces))
    query = o3d.core.Tensor((points.detach().cpu().double() - center.cpu()).float().numpy())
    return torch.from_numpy(scene.compute_occupancy(query, nsamples=3).numpy()).to(points.device) > 0.5


def cloud_from_mesh(mesh: Mesh, n: int, noise: float = 0.0, seed: int = 0) -> PointCloud:
    """A PointCloud of `n` area-uniform surface samples with exact normals and optional noise.

    `noise` is the standard deviation of isotropic Gaussian noise added to the positions, in the
    mesh's units; normals stay those of the clean surface.
    """
    if noise < 0:
        raise InputError(f"noise must be >= 0 (a standard deviation), got {noise}")
    generator = torch.Generator().manual_seed(seed)
    points, normals = sample_mesh_surface(mesh, n, generator)
    if noise > 0:
        points = points + noise * torch.randn(points.shape, dtype=points.dtype, generator=generator)
    return PointCloud(points, normals)
