"""Pure geometric operations on tensors: neighbours, normals, mesh sampling and distances.

Inputs and outputs are tensors in the caller's frame; nothing here normalises or learns.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import torch
from torch import Tensor

from neuralsurf.errors import ConfigError, InputError
from neuralsurf.structures import Mesh, PointCloud

# largest query x point count searched by brute force on a GPU (the bunny's sample pool: 1.25M queries x
# 100k points); beyond it, and on the CPU, a k-d tree
GPU_BRUTE_FORCE_PAIRS = 2**38


def take_rows(values: Tensor, index: Tensor) -> Tensor:
    """`values[index]`: the rows of Tensor["n ..."] `values` at Long or Int[Tensor, "..."] `index` (any shape), by
    `index_select`, which on the CPU gathers 2-3x faster than indexing."""
    return values.index_select(0, index.reshape(-1)).view(*index.shape, *values.shape[1:])


def knn(query: Tensor, points: Tensor, k: int = 1, within: float = math.inf) -> tuple[Tensor, Tensor]:
    """Exact k nearest neighbours of each query among `points`: brute force on a GPU (both tensors
    there, up to GPU_BRUTE_FORCE_PAIRS pairs), else a k-d tree on torch's CPU threads.

    Args:
        query: Float[Tensor, "m 3"].
        points: Float[Tensor, "n 3"].
        k: neighbours per query, 1 <= k <= n.
        within: only neighbours this close are found (the tree searches no farther: faster for queries
            with none near); the missing ones have distance inf and index n.
    Returns:
        distances Float[Tensor, "m k"] (query dtype) and indices Int[Tensor, "m k"] (int64).
    """
    if not 1 <= k <= len(points):
        raise InputError(f"knn needs 1 <= k <= {len(points)} (number of points), got k={k}")
    if query.is_cuda and points.is_cuda and len(query) * len(points) <= GPU_BRUTE_FORCE_PAIRS:
        distance, index = _brute_knn(query, points, k)
        beyond = distance > within
        return distance.masked_fill(beyond, math.inf), index.masked_fill(beyond, len(points))
    return _tree_knn(_kd_tree(points), query, k, within)


def _brute_knn(query: Tensor, points: Tensor, k: int, chunk_bytes: int = 2**30) -> tuple[Tensor, Tensor]:
    """`knn` by squared distances |q|^2 + |p|^2 - 2 q.p in chunks of queries (`chunk_bytes` of distances
    each); the distances of the chosen neighbours are recomputed from the coordinates, so the
    expansion's rounding can only swap near-ties."""
    points_f = points.float()
    squared = (points_f**2).sum(-1)
    nearest = (lambda d: d.argmin(1, keepdim=True)) if k == 1 else (lambda d: d.topk(k, 1, largest=False).indices)
    index = torch.cat([
        nearest(torch.addmm(squared, part, points_f.T, alpha=-2).add_((part**2).sum(-1, keepdim=True)))
        for part in query.float().split(max(1, chunk_bytes // (4 * len(points))))
    ])
    distance = (query[:, None, :] - points[index].to(query.dtype)).norm(dim=-1)
    distance, order = distance.sort(dim=1)  # re-sort after the exact recomputation
    return distance, index.gather(1, order)


def _kd_tree(points: Tensor):
    """scipy k-d tree of Float[Tensor, "n 3"] with sliding-midpoint splits: 3x faster queries far from the
    points (free space) than the balanced default."""
    from scipy.spatial import cKDTree

    return cKDTree(points.detach().cpu().double().numpy(), balanced_tree=False, compact_nodes=False)


def _tree_knn(tree, query: Tensor, k: int, within: float = math.inf) -> tuple[Tensor, Tensor]:
    """`knn` of Float[Tensor, "m 3"] queries in a built `_kd_tree`."""
    dist, index = tree.query(query.detach().cpu().double().numpy(), k=k, distance_upper_bound=within,
                             workers=torch.get_num_threads())
    dist, index = np.asarray(dist).reshape(len(query), k), np.asarray(index).reshape(len(query), k)
    return (
        torch.from_numpy(dist).to(query.dtype).to(query.device),
        torch.from_numpy(index).long().to(query.device),
    )


def _neighbour_pairs(coords: np.ndarray, k: int | None, radius: float | None) -> tuple[np.ndarray, np.ndarray]:
    """(row, column) index pairs of each point's neighbourhood, the point itself included.

    k only: the k nearest; radius only: every point within `radius`; both: at most the k nearest
    within `radius` (Open3D's hybrid search). coords: (n, 3) float64.
    """
    from scipy.spatial import cKDTree

    n = len(coords)
    tree = cKDTree(coords)
    if radius is None:
        _, index = tree.query(coords, k=k, workers=torch.get_num_threads())
        return np.repeat(np.arange(n), k), index.reshape(-1)
    if k is None:
        lists = tree.query_ball_point(coords, r=radius, workers=torch.get_num_threads(), return_sorted=False)
        counts = np.fromiter(map(len, lists), dtype=np.int64, count=n)
        return np.repeat(np.arange(n), counts), np.concatenate(lists).astype(np.int64)
    distance, index = tree.query(coords, k=k, distance_upper_bound=radius, workers=torch.get_num_threads())
    valid = np.isfinite(distance)
    return np.broadcast_to(np.arange(n)[:, None], index.shape)[valid], index[valid]


def _pca_normals(coords: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-variance direction of each neighbourhood given as (row, column) pairs.

    Returns normals (n, 3) and the neighbourhood sizes (n,). Covariances are accumulated from
    offsets to the query point, so far-from-origin clouds keep their precision.
    """
    n = len(coords)
    offsets = coords[cols] - coords[rows]  # (pairs, 3)
    count = np.bincount(rows, minlength=n).astype(np.float64)
    safe = np.maximum(count, 1.0)[:, None]
    mean = np.stack([np.bincount(rows, offsets[:, i], minlength=n) for i in range(3)], 1) / safe
    second = np.stack(
        [np.bincount(rows, offsets[:, i] * offsets[:, j], minlength=n) for i in range(3) for j in range(3)], 1
    ).reshape(n, 3, 3) / safe[:, :, None]
    covariance = second - mean[:, :, None] * mean[:, None, :]
    _, eigenvectors = np.linalg.eigh(covariance)
    return eigenvectors[..., 0], count


def estimate_normals(
    points: Tensor | PointCloud,
    k: int | None = 30,
    radius: float | None = None,
    orient: str | None = None,
    camera: Tensor | None = None,
    direction: Tensor | None = None,
) -> Tensor | PointCloud:
    """Unit normals by PCA of each point's neighbourhood, optionally oriented.

    The neighbourhood is the k nearest points (`radius=None`), every point within `radius`
    (`k=None`), or at most the k nearest within `radius` (both; Open3D's hybrid search). Points
    whose neighbourhood has fewer than 3 points get the plane of their 3 nearest (with a warning).

    Args:
        points: Float[Tensor, "n 3"] with n >= 3, or a PointCloud.
        k: neighbours per point (>= 3), or None with a radius.
        radius: search radius in the points' units, or None.
        orient: None (sign arbitrary), "mst", "camera" or "direction"; see `orient_normals`.
        camera: Float[Tensor, "3"] or Float[Tensor, "n 3"]: sensor position(s), for orient="camera".
        direction: Float[Tensor, "3"]: the direction normals should face, for orient="direction".
    Returns:
        Float[Tensor, "n 3"] (points' dtype and device) for a tensor input; for a PointCloud, the
        same cloud with these normals.

    Example:
        cloud = ns.geometry.estimate_normals(cloud, k=30, orient="mst")
    """
    if isinstance(points, PointCloud):
        normals = estimate_normals(points.points, k, radius, orient, camera, direction)
        return points.with_normals(normals)
    points = torch.as_tensor(points)
    if points.ndim != 2 or points.shape[1] != 3:
        raise InputError(f"normal estimation needs points of shape (n, 3), got {tuple(points.shape)}")
    if len(points) < 3:
        raise InputError(f"normal estimation needs at least 3 points, got {len(points)}")
    if k is None and radius is None:
        raise ConfigError("estimate_normals needs k, radius or both to define a neighbourhood; got neither")
    if k is not None and k < 3:
        raise ConfigError(f"estimate_normals needs k >= 3 neighbours to fit a plane, got k={k}")
    if radius is not None and not radius > 0:
        raise ConfigError(f"estimate_normals radius must be > 0 (in the points' units), got {radius}")
    _check_orientation(orient, camera, direction)
    coords = points.detach().cpu().double().numpy()
    rows, cols = _neighbour_pairs(coords, None if k is None else min(k, len(coords)), radius)
    normals, count = _pca_normals(coords, rows, cols)
    sparse = count < 3
    if sparse.any():
        warnings.warn(
            f"{int(sparse.sum())} of {len(coords)} points have fewer than 3 neighbours within "
            f"radius={radius}; their normals come from their 3 nearest neighbours instead "
            f"(raise the radius to avoid this)",
            stacklevel=2,
        )
        few_rows, few_cols = _neighbour_pairs(coords, 3, None)
        normals[sparse] = _pca_normals(coords, few_rows, few_cols)[0][sparse]
    result = torch.from_numpy(normals).to(device=points.device, dtype=points.dtype)
    if orient is None:
        return result
    return orient_normals(points, result, 30 if k is None else k, orient, camera, direction)


def project_to_quadrics(points: Tensor, normals: Tensor, k: int = 30) -> Tensor:
    """Move each point along its normal onto the quadric height field h(u, v) = a u^2 + b uv +
    c v^2 + d u + e v + f fitted by least squares to its k nearest neighbours, in the frame of its
    tangent plane (one step of moving least squares with second-order polynomials): removes noise
    across the surface, keeps the sampling along it, and, unlike a plane, does not flatten curved
    parts (a plane's bias is of order curvature x neighbourhood radius^2).

    Args:
        points: Float[Tensor, "n 3"]; normals: Float[Tensor, "n 3"] unit (e.g. `estimate_normals`);
        k: neighbours, at least 6 (the quadric's unknowns) and at most n.
    Returns:
        Float[Tensor, "n 3"]: the projected points, points + f n.
    """
    return points + quadric_heights(points, normals, k)[:, None] * normals


def quadric_heights(points: Tensor, normals: Tensor, k: int = 30, chunk: int = 65_536) -> Tensor:
    """Float[Tensor, "n"]: the height f along each point's unit normal of the quadric fitted to its k
    nearest neighbours (`project_to_quadrics`); `chunk` points at a time (bounds memory, same result).
    points, normals: Float[Tensor, "n 3"]."""
    if not 6 <= k <= len(points):
        raise ConfigError(f"projection onto local quadrics needs 6 <= k <= {len(points)} (points), got k={k}")
    tree = _kd_tree(points)
    return torch.cat([_quadric_height(points, normals[part], _tree_knn(tree, points[part], k)[1], part)
                      for part in (slice(i, i + chunk) for i in range(0, len(points), chunk))])


def _quadric_height(points: Tensor, normals: Tensor, index: Tensor, part: slice) -> Tensor:
    """Heights of points[part] (normals: theirs) over the quadric of their neighbours points[index]."""
    offset = points[index] - points[part, None]  # [n, k, 3]
    x_axis, y_axis = torch.eye(3, dtype=points.dtype)[:2]
    helper = torch.where(normals[:, :1].abs() < 0.9, x_axis, y_axis)  # any direction not along the normal
    t1 = torch.nn.functional.normalize(torch.cross(normals, helper, dim=-1), dim=-1)
    t2 = torch.cross(normals, t1, dim=-1)
    u, v, h = ((offset * axis[:, None]).sum(-1) for axis in (t1, t2, normals))  # [n, k] each
    scale = (u.square() + v.square()).mean(1, keepdim=True).sqrt().clamp_min(1e-12)  # conditioning
    u, v = u / scale, v / scale
    design = torch.stack([u * u, u * v, v * v, u, v, torch.ones_like(u)], -1)  # [n, k, 6]
    gram = design.transpose(1, 2) @ design + 1e-9 * torch.eye(6, dtype=points.dtype)
    coefficients = torch.linalg.solve(gram, (design.transpose(1, 2) @ h[..., None]))[..., 0]
    return coefficients[:, 5]


def _check_orientation(method: str | None, camera, direction) -> None:
    """ConfigError unless the orientation method and its reference (camera / direction) match."""
    if method not in (None, "mst", "camera", "direction"):
        raise ConfigError(
            f"unknown normal orientation {method!r}; choose None, 'mst', 'camera' or 'direction'"
        )
    if (method == "camera") != (camera is not None):
        raise ConfigError(
            "orient='camera' needs camera=<sensor position(s)>, and camera is only used with "
            f"orient='camera'; got orient={method!r}, camera={'given' if camera is not None else None}"
        )
    if (method == "direction") != (direction is not None):
        raise ConfigError(
            "orient='direction' needs direction=<3-vector>, and direction is only used with "
            f"orient='direction'; got orient={method!r}, "
            f"direction={'given' if direction is not None else None}"
        )


def orient_normals(
    points: Tensor,
    normals: Tensor,
    k: int = 30,
    method: str = "mst",
    camera: Tensor | None = None,
    direction: Tensor | None = None,
) -> Tensor:
    """Flip normals to consistent signs.

    - "mst" (Hoppe et al. 1992): signs propagate along a minimum spanning tree of the k-NN graph
      with weights 1 - |n_i . n_j|. In each connected component the root is the point with the
      largest x, whose normal is made to point along +x, so a closed surface's normals face outward.
    - "camera": each normal faces its sensor, n . (camera - p) >= 0 (one position or one per point).
    - "direction": each normal has n . direction >= 0.

    Args:
        points: Float[Tensor, "n 3"]; normals: Float[Tensor, "n 3"] unit, any signs.
        camera: Float[Tensor, "3"] or Float[Tensor, "n 3"], for "camera".
        direction: Float[Tensor, "3"], for "direction".
    Returns:
        Float[Tensor, "n 3"]: the same normals with consistent signs.
    """
    _check_orientation(method, camera, direction)
    if method is None:
        return normals
    nrm = normals.detach().cpu().double().numpy()
    coords = points.detach().cpu().double().numpy()
    if method == "mst":
        flip = _mst_flips(coords, nrm, k)
    else:
        reference = camera if method == "camera" else direction
        try:
            reference = np.asarray(torch.as_tensor(reference).cpu(), dtype=np.float64)
            reference = np.broadcast_to(reference, coords.shape)
        except ValueError:
            raise InputError(
                f"{method} must have shape (3,) or ({len(coords)}, 3), got {tuple(np.shape(reference))}"
            ) from None
        towards = reference - coords if method == "camera" else reference
        flip = (nrm * towards).sum(-1) < 0
    nrm[flip] *= -1
    return torch.from_numpy(nrm).to(normals)


def opposed_share(points: Tensor, normals: Tensor, k: int = 8, most: int = 20_000) -> float:
    """The share of Float[Tensor, "n 3"] `points` whose unit `normals` point against most of their `k` nearest
    neighbours' (a fixed random `most` of them, among themselves, for larger clouds): about 0 for oriented normals
    (under 0.1 % on the Stanford scans merged), about 0.4 for unoriented ones (random signs)."""
    if len(points) > most:
        chosen = torch.randperm(len(points), generator=torch.Generator().manual_seed(0))[:most].to(points.device)
        points, normals = points[chosen], normals[chosen]
    _, index = knn(points, points, min(k + 1, len(points)))
    agreement = (normals[index[:, 1:]] * normals[:, None]).sum(-1).sign().sum(1)
    return float((agreement < 0).double().mean())


def _mst_flips(coords: np.ndarray, normals: np.ndarray, k: int) -> np.ndarray:
    """Bool (n,): which normals to flip for consistent signs along the MST (see `orient_normals`).

    A virtual node n joins every component's root so that one breadth-first search yields each
    point's parent; signs then compose up the tree by pointer jumping (log2(depth) vector steps).
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import breadth_first_order, connected_components, minimum_spanning_tree

    n = len(coords)
    k = max(1, min(k, n - 1))
    rows, cols = _neighbour_pairs(coords, k + 1, None)
    keep = rows != cols
    rows, cols = rows[keep], cols[keep]
    unit = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
    # kept > 0: a sparse graph drops zero weights (and float32 normals can give |cos| > 1)
    weights = np.maximum(1.0 - np.abs((unit[rows] * unit[cols]).sum(-1)), 0.0) + 1e-9
    graph = coo_matrix((weights, (rows, cols)), shape=(n, n)).tocsr()
    tree = minimum_spanning_tree(graph.maximum(graph.T))
    tree = tree.maximum(tree.T)
    n_components, labels = connected_components(tree, directed=False)
    order = np.lexsort((coords[:, 0], labels))  # by component, then x: the last of each is its root
    roots = order[np.flatnonzero(np.append(labels[order][1:] != labels[order][:-1], True))]
    tree, virtual = tree.tocoo(), np.full(n_components, n)
    edges = (np.concatenate([tree.row, roots, virtual]), np.concatenate([tree.col, virtual, roots]))
    tree = coo_matrix((np.ones(len(edges[0])), edges), shape=(n + 1, n + 1)).tocsr()
    _, parent = breadth_first_order(tree, n, directed=False, return_predecessors=True)
    parent[n] = n
    # relative sign of each edge to its parent; the roots' edge to the virtual node aligns them with +x
    sign = np.where((normals * normals[np.minimum(parent[:n], n - 1)]).sum(-1) < 0, -1.0, 1.0)
    sign[roots] = np.where(normals[roots, 0] < 0, -1.0, 1.0)
    sign = np.append(sign, 1.0)
    ancestor = parent.copy()
    while (ancestor != n).any():
        sign = sign * sign[ancestor]
        ancestor = ancestor[ancestor]
    return sign[:n] < 0


MULTINOMIAL_CATEGORIES = 1 << 24
"""The most categories `torch.multinomial` draws from."""


def area_weighted_faces(areas: Tensor, n: int, generator: torch.Generator | None = None) -> Tensor:
    """Long[Tensor, "n"]: faces drawn with replacement in proportion to their Float64[Tensor, "f"] `areas`: by
    `torch.multinomial`, or for more than `MULTINOMIAL_CATEGORIES` faces (a mesh extracted at 1,024^3 and subdivided)
    by inverse transform of the areas' cumulative sum."""
    if len(areas) <= MULTINOMIAL_CATEGORIES:
        return torch.multinomial(areas, n, replacement=True, generator=generator)
    cumulative = areas.cumsum(0)
    draws = torch.rand(n, dtype=cumulative.dtype, generator=generator) * cumulative[-1]
    return torch.searchsorted(cumulative, draws, right=True).clamp_max_(len(areas) - 1)


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
    face = area_weighted_faces(areas, n, generator)
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
    scene, query = _centred_query(points, mesh, "point_to_mesh_distance")
    return torch.from_numpy(scene.compute_distance(query).numpy()).to(points)


def closest_on_mesh(points: Tensor, mesh: Mesh) -> tuple[Tensor, Tensor]:
    """Each point's exact distance to the mesh (as `point_to_mesh_distance`) and the face holding its
    closest surface point, from one BVH of the mesh.

    Args:
        points: Float[Tensor, "n 3"]; mesh: non-empty Mesh in the same frame.
    Returns:
        Float[Tensor, "n"] distances in the points' dtype, Int64[Tensor, "n"] face indices.
    """
    scene, query = _centred_query(points, mesh, "closest_on_mesh")
    distance = torch.from_numpy(scene.compute_distance(query).numpy()).to(points)
    faces = scene.compute_closest_points(query)["primitive_ids"].numpy().astype(np.int64)
    return distance, torch.from_numpy(faces).to(points.device)


def _centred_query(points: Tensor, mesh: Mesh, caller: str):
    """Open3D's ray-casting scene of the mesh and the query points, both re-centred on the mesh's mean
    vertex (relative precision in float32)."""
    if mesh.is_empty:
        raise InputError(f"{caller} needs a mesh with faces, got an empty mesh")
    import open3d as o3d

    center = mesh.vertices.double().mean(0)
    scene = _raycasting_scene(Mesh(mesh.vertices.double() - center, mesh.faces))
    query = (points.detach().cpu().double() - center.cpu()).float().numpy()
    return scene, o3d.core.Tensor(query)


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


def noisy_cloud(surface: Tensor, n_points: int, noise: float, seed: int) -> Tensor:
    """`n_points` of `surface` (Float[Tensor, "m 3"]) at random plus N(0, noise^2) on each coordinate."""
    generator = torch.Generator().manual_seed(seed)
    pick = torch.randperm(len(surface), generator=generator)[:n_points]
    return surface[pick] + noise * torch.randn(len(pick), 3, generator=generator, dtype=surface.dtype)


# ---------------------------------------------------------------------------------------------
# mesh vertices


def merge_duplicate_vertices(
    vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Merge vertices with bit-identical position (and colour), keeping first-occurrence order.

    vertices (v, 3), faces (f, 3), colors (v, 3) or None -> the same with v' <= v vertices; the
    faces keep their order and orientation. Nothing changes when there are no duplicates.
    """
    key = vertices + 0.0  # -0.0 -> 0.0
    if colors is not None:
        key = np.concatenate([key, colors.astype(key.dtype)], axis=1)
    key = np.ascontiguousarray(key)
    rows = key.view(np.dtype((np.void, key.dtype.itemsize * key.shape[1]))).ravel()
    _, first, inverse = np.unique(rows, return_index=True, return_inverse=True)
    if len(first) == len(vertices):
        return vertices, faces, colors
    order = np.argsort(first)  # unique rows by first occurrence
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    keep = first[order]
    new_faces = rank[inverse.ravel()][faces]
    return vertices[keep], new_faces, None if colors is None else colors[keep]


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals: vertices (v, 3), faces (f, 3) -> (v, 3) in the vertices' dtype.

    Each face adds its cross product (b - a) x (c - a) (twice its area times its unit normal) to its
    three vertices, so the normals point to the side from which the faces are counter-clockwise:
    outward on a neuralsurf mesh. A vertex of no face of non-zero area gets (0, 0, 0).
    """
    corners = vertices.astype(np.float64)[faces]
    weighted = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    sums = np.zeros((len(vertices), 3))
    for k in range(3):
        np.add.at(sums, faces[:, k], weighted)
    length = np.linalg.norm(sums, axis=1, keepdims=True)
    normals = np.divide(sums, length, out=np.zeros_like(sums), where=length > 0)
    return normals.astype(vertices.dtype if vertices.dtype in (np.float32, np.float64) else np.float64)


# ---------------------------------------------------------------------------------------------
# oriented point clouds: spacing, areas, generalised winding number


SPACING_QUERIES = 100_000
"""`cloud_spacing` reads the median of this many points' nearest-neighbour distances (a fixed random draw): on 5M
points the whole cloud's queries took 17 s and 100k of them 3 s, their median 0.3 % off."""


ROUNDING = 1e-3
"""The most by which float32 may round a coordinate, as a share of the finest length that matters there."""


def float32_holds(far: float, length: float) -> bool:
    """Whether float32 holds coordinates up to `far` from the origin to within `ROUNDING` of `length` (a grid's
    cell, a mesh's edge). False for data far from the origin for its detail, such as georeferenced scans: they need
    float64, or an origin nearer to them."""
    return far * float(torch.finfo(torch.float32).eps) <= ROUNDING * length


def local_origin(points: Tensor, length: float) -> Tensor:
    """Float64[Tensor, "3"]: where to put the origin before working on Float[Tensor, "n 3"] `points` in float32: the
    origin itself where float32 holds them to `length` (`float32_holds`; subtracting it changes nothing), else
    their mean."""
    if float32_holds(float(points.detach().abs().max()), length):
        return torch.zeros(3, dtype=torch.float64, device=points.device)
    return points.detach().double().mean(0)


SPACING_NEIGHBOURS = 8
"""`cloud_spacing` reads this many neighbours of a point, so that repeats of it (a cloud saved twice) are skipped."""


def cloud_spacing(points: Tensor) -> float:
    """Median distance from a point to its nearest point elsewhere (its exact repeats skipped), over all
    Float[Tensor, "n 3"] `points` or a fixed random `SPACING_QUERIES` of them. Raises InputError when every point
    read has `SPACING_NEIGHBOURS` - 1 repeats or more."""
    query = points
    if len(points) > SPACING_QUERIES:
        chosen = torch.randperm(len(points), generator=torch.Generator().manual_seed(0))[:SPACING_QUERIES]
        query = points[chosen.to(points.device)]
    distance, _ = knn(query, points, min(SPACING_NEIGHBOURS, max(len(points), 2)))
    others = distance[:, 1:]  # the first is the point itself
    nearest = torch.where(others > 0, others, math.inf).min(1).values
    nearest = nearest[nearest.isfinite()]
    if not len(nearest):
        raise InputError(f"the {len(points)} points have no spacing: each repeats {SPACING_NEIGHBOURS - 1} others or "
                         f"more at exactly its position; merge the repeated points")
    return float(nearest.median())


def isolated_points(points: Tensor, k: int = 8, factor: float = 10.0) -> Tensor:
    """Bool[Tensor, "n"]: which of Float[Tensor, "n 3"] `points` have their `k`-th nearest other point more than
    `factor` times the cloud's median such distance away (statistical outlier removal's test): stray points
    that no surface at the cloud's spacing passes through. None where that median is 0 (most points repeated)."""
    distance, _ = knn(points, points, min(k + 1, len(points)))
    kth = distance[:, -1]
    typical = float(kth.median())
    return kth > factor * typical if typical > 0 else torch.zeros(len(points), dtype=torch.bool, device=points.device)


def colors_from_points(vertices: Tensor, cloud: PointCloud, k: int = 4) -> Tensor:
    """Float[Tensor, "v 3"]: the colour of each of Float[Tensor, "v 3"] `vertices`, the inverse-distance mean of its
    `k` nearest points' in a coloured `cloud` (the same frame)."""
    distance, index = knn(vertices, cloud.points, min(k, len(cloud)))
    weight = 1 / distance.double().clamp_min(1e-12)
    colors = cloud.colors.to(vertices.device).double()
    return ((weight[..., None] * colors[index]).sum(1) / weight.sum(1, keepdim=True)).to(vertices.dtype)


def point_areas(points: Tensor, k: int = 8) -> Tensor:
    """Surface area each point stands for, pi r_k^2 / k with r_k the distance to its k-th nearest
    neighbour (k points per disc of that radius). points: Float[Tensor, "n 3"] -> Float[Tensor, "n"]."""
    distance, _ = knn(points, points, min(k + 1, len(points)))
    return math.pi * distance[:, -1] ** 2 / k


def cloud_winding_number(query: Tensor, points: Tensor, normals: Tensor, areas: Tensor, chunk: int = 512) -> Tensor:
    """Generalised winding number of an oriented point cloud (Barill et al. 2018, direct sum):
    w(q) = sum_i a_i n_i . (p_i - q) / (4 pi |p_i - q|^3), about 1 inside a closed surface and 0 outside,
    away from the points (closer than their spacing it is noisy).

    Args:
        query: Float[Tensor, "m 3"]; points, normals: Float[Tensor, "n 3"] (unit, outward);
        areas: Float[Tensor, "n"] (`point_areas`); chunk: queries per step (memory chunk x n).
    Returns:
        Float[Tensor, "m"].
    """
    offset = (points * normals).sum(-1)  # n_i . p_i
    squared = (points**2).sum(-1)
    # two (chunk, n) buffers reused by every chunk: allocating them anew each time grew glibc's heap
    # by about one buffer per chunk (4.5 GB for the bunny's 250k free points)
    dot_buffer = query.new_empty(min(chunk, len(query)), len(points))
    r2_buffer = torch.empty_like(dot_buffer)
    out = []
    for part in query.split(chunk):
        dot = torch.addmm(offset, part, normals.T, alpha=-1, out=dot_buffer[: len(part)])  # n_i . (p_i - q)
        r2 = torch.add(squared, (part**2).sum(-1, keepdim=True), out=r2_buffer[: len(part)])
        inverse = r2.addmm_(part, points.T, alpha=-2).clamp_min_(1e-12).rsqrt_()
        out.append(dot.mul_(inverse.pow_(3)) @ areas)  # pow_(3): one pass where three products took three
    return torch.cat(out) / (4 * math.pi) if out else query.new_zeros(0)
