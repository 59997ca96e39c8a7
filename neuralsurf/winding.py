"""Inside and outside of imperfect triangle meshes: generalised winding numbers (Jacobson et al. 2013).

Real CAD meshes are rarely watertight: open boundaries, duplicated or inner sheets, overlapping
closed parts and flipped faces. Ray parity (`geometry.mesh_contains`) breaks on all of them; the
winding number `w(q) = sum_t Omega_t(q) / (4 pi)`, the signed solid angles of the triangles seen from
`q`, is 1 inside and 0 outside a closed, outward surface, varies smoothly across holes, and counts
overlapping parts and coincident sheets as 2 (still inside at the threshold 1/2).

- `winding_number(query, mesh)`: exact solid angles near each query, a second-order dipole expansion
  of far clusters of triangles (Barill et al. 2018) beyond `near` grid cells; `approximate=False` sums
  every triangle exactly.
- `orient_outward(mesh)`: faces made consistent across manifold edges, each connected patch then
  turned to face where more random rays escape to infinity (visibility, as Takayama et al. 2014):
  repairs flipped faces and inward patches, which the winding number needs.
- `signed_distance(points, mesh)` (unsigned distance to the triangles, sign from the winding number)
  and `inside(points, mesh)`; `boundary_faces(mesh)`: the faces between inside and outside (inner
  and stray sheets left out), the surface a shape's distances and samples should come from.
- `damage_mesh(mesh, ...)`: the defects of CAD meshes applied to a clean mesh (holes, coincident
  duplicated sheets, inner sheets, flipped faces), with where they are, for testing the signs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from neuralsurf.errors import ConfigError, InputError
from neuralsurf.geometry import point_to_mesh_distance
from neuralsurf.io.meshes import vertex_normals
from neuralsurf.structures import Mesh

INSIDE_THRESHOLD = 0.5
"""A point is inside where its winding number is at least this."""


def _check(points: Tensor, mesh: Mesh, caller: str) -> None:
    if mesh.is_empty:
        raise InputError(f"{caller} needs a mesh with faces, got an empty mesh")
    if not (isinstance(points, Tensor) and points.ndim == 2 and points.shape[-1] == 3):
        shape = tuple(points.shape) if isinstance(points, Tensor) else type(points).__name__
        raise InputError(f"{caller} takes points of shape (n, 3) as a tensor, got {shape}")


def _solid_angles(d: Tensor) -> Tensor:
    """Float[Tensor, "..."]: signed solid angle / (4 pi) of triangles whose corners, relative to the
    query, are d: Float[Tensor, "... 3 3"] (Van Oosterom and Strackee 1983)."""
    a, b, c = d.unbind(-2)
    la, lb, lc = d.norm(dim=-1).unbind(-1)
    det = (a * torch.linalg.cross(b, c)).sum(-1)
    den = la * lb * lc + (a * b).sum(-1) * lc + (b * c).sum(-1) * la + (c * a).sum(-1) * lb
    return torch.atan2(det, den) / (2 * math.pi)


def triangle_solid_angles(query: Tensor, triangles: Tensor) -> Tensor:
    """Sum over triangles of their signed solid angle seen from each query, divided by 4 pi.

    Args:
        query: Float[Tensor, "m 3"]; triangles: Float[Tensor, "f 3 3"] (corners counter-clockwise
        seen from outside).
    Returns:
        Float[Tensor, "m"]: each query's winding number with respect to these triangles.
    """
    return _solid_angles(triangles[None] - query[:, None, None, :]).sum(-1)


def _exact(query: Tensor, triangles: Tensor, elements: int) -> Tensor:
    """`triangle_solid_angles` in row chunks of about `elements` query-triangle pairs."""
    if len(triangles) == 0:
        return query.new_zeros(len(query))
    rows = max(1, elements // len(triangles))
    return torch.cat([triangle_solid_angles(part, triangles) for part in query.split(rows)])


@dataclass(frozen=True)
class _Clusters:
    """Small triangles grouped by the grid cell of their centroid, with each cell's expansion."""

    key: Tensor
    """Int[Tensor, "c"]: sorted linear index of each non-empty cell."""
    order: Tensor
    """Int[Tensor, "s"]: small triangles sorted by cell; `first[k]:first[k + 1]` are cell k's."""
    first: Tensor
    centre: Tensor
    """Float[Tensor, "c 3"]: area-weighted centroid of each cell's triangles."""
    normal: Tensor
    """Float[Tensor, "c 3"]: sum of the area-weighted normals (the dipole)."""
    moment: Tensor
    """Float[Tensor, "c 3 3"]: sum of area * normal (centroid - centre)^T (the second-order term)."""
    large: Tensor
    """Int[Tensor, "l"]: triangles wider than half a cell, always summed exactly."""


def _clusters(triangles: Tensor, size: float, cells: int) -> _Clusters:
    """Cluster the triangles (Float[Tensor, "f 3 3"], in [-0.5, 0.5]^3) on `cells`^3 cubes of side `size`."""
    centroid = triangles.mean(1)
    small = (triangles - centroid[:, None]).norm(dim=-1).amax(-1) <= size / 2
    index = ((centroid + 0.5) / size).floor().long().clamp(0, cells - 1)
    key = (index[:, 0] * cells + index[:, 1]) * cells + index[:, 2]
    small_ids = torch.nonzero(small).squeeze(1)
    unique, row = torch.unique(key[small_ids], return_inverse=True)
    order = small_ids[torch.argsort(row, stable=True)]
    counts = torch.bincount(row, minlength=len(unique))
    a, b, c = triangles[small_ids].unbind(1)
    area_normal = 0.5 * torch.linalg.cross(b - a, c - a)
    weight = area_normal.norm(dim=-1) + 1e-12  # degenerate triangles still place their cell's centre

    def total(values: Tensor) -> Tensor:
        return values.new_zeros(len(unique), *values.shape[1:]).index_add_(0, row, values)

    centre = total(weight[:, None] * centroid[small_ids]) / total(weight)[:, None]
    offset = centroid[small_ids] - centre[row]
    return _Clusters(unique, order, torch.cat([counts.new_zeros(1), counts.cumsum(0)]), centre, total(area_normal),
                     total(area_normal[:, :, None] * offset[:, None, :]), torch.nonzero(~small).squeeze(1))


def _far_field(points: Tensor, clusters: _Clusters, far: Tensor) -> Tensor:
    """Sum over the clusters marked `far` (Bool[Tensor, "m k"]) of their second-order expansion at
    each of Float[Tensor, "m 3"] points -> Float[Tensor, "m"].

    With r = centre - q: w = (N . r + tr(M) - 3 r^T S r / |r|^2) / (4 pi |r|^3), S = (M + M^T) / 2, from
    K(r) = r / (4 pi |r|^3) and its Jacobian (I / |r|^3 - 3 r r^T / |r|^5) / (4 pi). Every term
    expanded in q is a matrix product (far clusters are a cell or more away, so float32 keeps its
    relative precision); the near ones are computed too and masked out.
    """
    c, n = clusters.centre, clusters.normal
    s = (clusters.moment + clusters.moment.transpose(1, 2)) / 2
    sc = (s @ c[:, :, None])[..., 0]  # k 3
    upper = torch.stack([s[:, 0, 0], s[:, 1, 1], s[:, 2, 2], 2 * s[:, 0, 1], 2 * s[:, 0, 2], 2 * s[:, 1, 2]], -1)
    q = points
    quadratic = torch.stack([q[:, 0] ** 2, q[:, 1] ** 2, q[:, 2] ** 2, q[:, 0] * q[:, 1], q[:, 0] * q[:, 2],
                             q[:, 1] * q[:, 2]], -1)
    r2 = ((c * c).sum(-1) - 2 * q @ c.T + (q * q).sum(-1, keepdim=True)).clamp_min_(1e-12)
    dipole = (n * c).sum(-1) - q @ n.T
    rmr = (c * sc).sum(-1) - 2 * q @ sc.T + quadratic @ upper.T
    trace = clusters.moment.diagonal(dim1=-2, dim2=-1).sum(-1)
    inverse = r2.reciprocal_()
    value = (dipole + trace - 3 * rmr * inverse) * inverse * inverse.sqrt()
    return torch.where(far, value, 0.0).sum(-1) / (4 * math.pi)


def _clustered(points: Tensor, triangles: Tensor, cells: int, near: int, elements: int) -> Tensor:
    """The winding number at Float[Tensor, "m 3"] points of Float[Tensor, "f 3 3"] triangles (both in
    the mesh's unit box): the exact sum over the triangles of the clusters within `near` cells of a
    point's cell and over the large triangles, the expansion of every other cluster."""
    size = 1.0 / cells
    clusters = _clusters(triangles, size, cells)
    lengths = clusters.first[1:] - clusters.first[:-1]
    steps = torch.arange(-near, near + 1)
    offsets = torch.cartesian_prod(steps, steps, steps)  # o 3
    cell = ((points + 0.5) / size).floor().long()  # outside the box: no cluster is near
    out = _exact(points, triangles[clusters.large], elements)
    rows = max(1, min(elements // (8 * len(clusters.key) + 1), elements // 64))
    for start in range(0, len(points), rows):
        part = slice(start, start + rows)
        neighbour = cell[part, None] + offsets  # q o 3
        valid = ((neighbour >= 0) & (neighbour < cells)).all(-1)
        key = (neighbour[..., 0] * cells + neighbour[..., 1]) * cells + neighbour[..., 2]
        found = torch.searchsorted(clusters.key, key).clamp_max(len(clusters.key) - 1)
        valid &= clusters.key[found] == key
        local, slot = torch.nonzero(valid, as_tuple=True)
        cluster = found[local, slot]
        far = torch.ones(len(key), len(clusters.key), dtype=torch.bool)
        far[local, cluster] = False
        out[part] += _far_field(points[part], clusters, far)
        count = lengths[cluster]
        pair_query = torch.repeat_interleave(local + start, count)
        base = torch.repeat_interleave(clusters.first[cluster] - (count.cumsum(0) - count), count)
        pair_triangle = clusters.order[base + torch.arange(len(base))]
        for chunk in range(0, len(pair_query), elements):
            q, t = pair_query[chunk:chunk + elements], pair_triangle[chunk:chunk + elements]
            out.index_add_(0, q, _solid_angles(triangles[t] - points[q][:, None]))
    return out


def winding_number(query: Tensor, mesh: Mesh, *, approximate: bool = True, near: int = 1,
                   cells: int | None = None, elements: int = 2**20) -> Tensor:
    """Generalised winding number of a triangle mesh at each query point.

    About 1 inside and 0 outside a closed surface with outward (counter-clockwise) faces; across a
    hole it varies smoothly, overlapping closed parts count 2. With `approximate` (and 2048 faces or
    more), triangles are clustered on a grid of `cells`^3 cubes over the mesh's box (default from the
    face count); clusters more than `near` cells from a query's cell enter by their second-order
    dipole expansion (Barill et al. 2018), the others and triangles wider than half a cell exactly:
    within a few hundredths of the exact sum at `near=1` (a few thousandths at 2, at about twice the
    time). Computed in float32 in the mesh's unit box (solid angles do not change with translation
    and scale).

    Args:
        query: Float[Tensor, "m 3"]; mesh: Mesh in the same frame.
        elements: query-triangle pairs per chunk (memory: about 200 bytes each).
    Returns:
        Float[Tensor, "m"] on the query's device, in its dtype.
    """
    _check(query, mesh, "winding_number")
    if near < 1:
        raise ConfigError(f"winding_number: near must be >= 1 grid cells, got {near}")
    vertices = mesh.vertices.detach().cpu().double()
    low, high = vertices.min(0).values, vertices.max(0).values
    centre, extent = (low + high) / 2, float((high - low).max().clamp_min(1e-12))
    # solid angles are invariant to translation and scale: work in the mesh's unit box
    triangles = ((vertices - centre) / extent)[mesh.faces.cpu()].to(torch.float32)
    points = ((query.detach().cpu().double() - centre) / extent).to(torch.float32)
    if not approximate or len(triangles) < 2048:
        return _exact(points, triangles, elements).to(query)
    cells = cells or int(np.clip(round(math.sqrt(1.25 * math.sqrt(len(triangles)))), 4, 64))
    return _clustered(points, triangles, cells, near, elements).to(query)


def inside(points: Tensor, mesh: Mesh, **options) -> Tensor:
    """Bool[Tensor, "n"]: points whose winding number is at least 1/2 (`winding_number`'s options)."""
    return winding_number(points, mesh, **options) >= INSIDE_THRESHOLD


def signed_distance(points: Tensor, mesh: Mesh, **options) -> Tensor:
    """Float[Tensor, "n"]: the exact distance to the mesh's triangles, negative where the winding
    number says inside (`inside`). Right for open, multi-sheet meshes whose faces face outward (run
    `orient_outward` first when they may not)."""

    _check(points, mesh, "signed_distance")
    distance = point_to_mesh_distance(points, mesh)
    return torch.where(inside(points, mesh, **options).to(distance.device), -distance, distance)


def _weighted_median(values: Tensor, weights: Tensor, groups: Tensor, n: int) -> Tensor:
    """Float64[Tensor, "n"]: the weighted median of `values` (Float[Tensor, "k"], `weights` likewise)
    within each of `n` groups (`groups`: Int[Tensor, "k"] in 0 .. n - 1); an empty group gets 1/2."""
    order = np.lexsort((values.numpy(), groups.numpy()))  # by group, then by value
    g, v, w = groups.numpy()[order], values.numpy()[order], weights.numpy()[order] + 1e-30
    cumulative = np.cumsum(w)
    before = np.concatenate([[0.0], cumulative])[np.searchsorted(g, np.arange(n))]
    reached = cumulative - before[g] >= np.bincount(g, weights=w, minlength=n)[g] / 2
    index = np.flatnonzero(reached)
    present, first = np.unique(g[index], return_index=True)  # each group's first value past half its weight
    median = np.full(n, 0.5)
    median[present] = v[index[first]]
    return torch.from_numpy(median)


def boundary_faces(mesh: Mesh, offset: float = 1e-3, **options) -> Tensor:
    """Bool[Tensor, "f"]: faces between inside and outside; faces should face outward (`orient_outward`).

    1. Open sheets inside or outside the shape go first, whole: an open patch (faces joined across
       manifold edges, `consistent_patches`, with a border) shifts the winding number near it by up to
       1/2 (an inner sheet just below the surface puts the layer between them at 1/2), so it would
       spoil the test below. Each open patch is scored by the area-weighted median over its faces of
       the winding number midway across the face (the mean of its two sides: what the rest of the mesh
       says there, without the face's own jump of 1): about 1/2 on the surface, 1 for an inner sheet,
       0 for a stray one. Patches scored 3/4 or more, or under 1/4, are removed and the rest scored
       again without them, until none is.
    2. Of the faces left, those where the winding number (of the faces left) is at least 1/2 on
       exactly one side, `offset` (a fraction of the longest side) along the normal from the centroid,
       or a quarter of the face's height where it is narrower (slivers): faces of closed parts inside
       others (winding number 2 and 1) are not. Keep `offset` below half the thinnest wall.
    """
    if mesh.is_empty:
        raise InputError("boundary_faces needs a mesh with faces, got an empty mesh")
    vertices, faces = mesh.vertices.detach().cpu().double(), mesh.faces.cpu()
    patch, _ = consistent_patches(faces)
    patches = int(patch.max()) + 1
    candidate = torch.zeros(patches, dtype=torch.bool)
    candidate[patch[_border_faces(faces)]] = True  # open patches
    extent = float((vertices.max(0).values - vertices.min(0).values).max().clamp_min(1e-12))
    corners = vertices[faces]
    cross = torch.linalg.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    # a face's own jump of 1 is seen only within about its width: a sliver narrower than the offset
    # (marching cubes makes them on thin rims) is tested at a quarter of its height instead
    area = cross.norm(dim=-1)  # twice each face's area
    height = area / (corners - corners.roll(1, 1)).norm(dim=-1).amax(-1).clamp_min(1e-300)
    distance = torch.clamp(height / 4, max=offset * extent)
    step = distance[:, None] * torch.nn.functional.normalize(cross, dim=-1)
    centroid = corners.mean(1)
    sides = torch.cat([centroid + step, centroid - step])  # front, back
    wind = winding_number(sides, Mesh(vertices, faces), **options)
    active = torch.ones(patches, dtype=torch.bool)
    while True:
        front, back = wind.chunk(2)
        kept = active[patch]
        score = _weighted_median((front + back)[kept] / 2, area[kept], patch[kept], patches)
        sheet = active & candidate & ((score >= 0.75) | (score < 0.25))
        if not sheet.any():
            break
        active &= ~sheet
        # winding numbers add up over faces: take the sheets' own (exact) part out
        wind = wind - _exact(sides, corners[sheet[patch]], 2**20)
    return (active[patch] & ((front >= INSIDE_THRESHOLD) != (back >= INSIDE_THRESHOLD))).to(mesh.faces.device)


def _border_faces(faces: Tensor) -> Tensor:
    """Bool[Tensor, "f"]: faces with an edge no other face has (Int[Tensor, "f 3"] faces)."""
    f = faces.numpy()
    edges = np.sort(np.stack([f, np.roll(f, -1, axis=1)], -1).reshape(-1, 2), axis=1)
    _, edge, count = np.unique(edges, axis=0, return_inverse=True, return_counts=True)
    return torch.from_numpy((count[edge.ravel()] == 1).reshape(-1, 3).any(1))


# ----------------------------------------------------------------------------- orientation


def consistent_patches(faces: Tensor) -> tuple[Tensor, Tensor]:
    """Patches of faces joined across manifold edges (shared by exactly two faces), and the flips
    that make each patch's orientation agree with its first face.

    Args:
        faces: Int[Tensor, "f 3"].
    Returns:
        patch Int[Tensor, "f"] (0 .. patches - 1) and flip Bool[Tensor, "f"]. A non-orientable patch
        (a Moebius strip) keeps its faces as they are.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    f = faces.cpu().numpy()
    n = len(f)
    directed = np.stack([f, np.roll(f, -1, axis=1)], -1).reshape(-1, 2)  # (3f, 2) half-edges
    owner = np.repeat(np.arange(n), 3)
    undirected = np.sort(directed, axis=1)
    _, edge, count = np.unique(undirected, axis=0, return_inverse=True, return_counts=True)
    edge = edge.ravel()
    manifold = count[edge] == 2
    ids = np.nonzero(manifold)[0]
    ids = ids[np.argsort(edge[ids], kind="stable")]  # the two half-edges of each manifold edge side by side
    first, second = ids[0::2], ids[1::2]
    same = directed[first, 0] == directed[second, 0]  # both faces run the edge the same way: inconsistent
    fa, fb = owner[first], owner[second]
    # node 2i: face i as stored, 2i + 1: face i flipped
    rows = np.concatenate([2 * fa, 2 * fa + 1])
    cols = np.concatenate([2 * fb + same, 2 * fb + 1 - same])
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(2 * n, 2 * n))
    _, label = connected_components(graph, directed=False)
    kept, flipped = label[0::2], label[1::2]
    canonical = np.minimum(kept, flipped)
    flip = (flipped == canonical) & (kept != flipped)
    _, patch = np.unique(canonical, return_inverse=True)
    return torch.from_numpy(patch.ravel()).long(), torch.from_numpy(flip)


def _hemisphere(normals: np.ndarray, rays: int, rng: np.random.Generator) -> np.ndarray:
    """(n, rays, 3) random unit directions on the side of each normal (n, 3)."""
    d = rng.normal(size=(len(normals), rays, 3))
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    side = np.sign((d * normals[:, None]).sum(-1, keepdims=True))
    return d * np.where(side == 0, 1.0, side)


def orient_outward(mesh: Mesh, samples: int = 4096, rays: int = 16, seed: int = 0) -> Mesh:
    """The mesh with every face turned outward: faces made consistent within each patch
    (`consistent_patches`), then each patch flipped when fewer random rays escape to infinity from
    its front side than from its back (Open3D ray casting from about `samples` area-weighted points,
    at least one a patch, `rays` a side). A patch seen from neither side (enclosed) keeps the
    orientation of its first face.

    Returns:
        Mesh with the same vertices and reoriented faces (vertex colours kept).
    """
    import open3d as o3d

    if mesh.is_empty:
        raise InputError("orient_outward needs a mesh with faces, got an empty mesh")
    patch, flip = consistent_patches(mesh.faces)
    faces = mesh.faces.cpu().clone()
    faces[flip] = faces[flip].flip(1)
    vertices = mesh.vertices.detach().cpu().double()
    centre = vertices.mean(0)
    extent = float((vertices.max(0).values - vertices.min(0).values).max().clamp_min(1e-12))
    unit = ((vertices - centre) / extent).numpy()
    tri = unit[faces.numpy()]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = 0.5 * np.linalg.norm(cross, axis=1)
    normal = cross / np.maximum(2 * area, 1e-300)[:, None]
    patches = int(patch.max()) + 1
    p = patch.numpy()
    rng = np.random.default_rng(seed)
    patch_area = np.bincount(p, weights=area, minlength=patches)
    per_patch = np.clip(np.round(samples * patch_area / max(patch_area.sum(), 1e-300)), 1, None).astype(int)
    picks = []  # area-weighted faces of each patch
    order = np.argsort(p, kind="stable")
    starts = np.concatenate([[0], np.bincount(p, minlength=patches).cumsum()])
    for k in range(patches):
        members = order[starts[k]:starts[k + 1]]
        weight = area[members] + 1e-30
        picks.append(rng.choice(members, size=per_patch[k], p=weight / weight.sum()))
    face = np.concatenate(picks)
    u, v = rng.uniform(size=(2, len(face), 1))
    fold = (u + v) > 1
    u, v = np.where(fold, 1 - u, u), np.where(fold, 1 - v, v)
    point = tri[face, 0] + u * (tri[face, 1] - tri[face, 0]) + v * (tri[face, 2] - tri[face, 0])
    n = normal[face]
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(unit.astype(np.float32)), o3d.core.Tensor(faces.numpy().astype(np.uint32)))
    escapes = []
    for side in (1.0, -1.0):
        direction = _hemisphere(side * n, rays, rng)
        origin = np.broadcast_to((point + side * 1e-4 * n)[:, None], direction.shape)
        casting = np.concatenate([origin, direction], -1).reshape(-1, 6).astype(np.float32)
        hit = scene.cast_rays(o3d.core.Tensor(casting))["t_hit"].numpy().reshape(len(face), rays)
        escapes.append(np.isinf(hit).mean(1))
    score = np.bincount(p[face], weights=escapes[0] - escapes[1], minlength=patches)
    turn = torch.from_numpy(score < 0)[patch]
    faces[turn] = faces[turn].flip(1)
    return Mesh(mesh.vertices, faces.to(mesh.faces.device), mesh.vertex_colors)


# ----------------------------------------------------------------------------- damaged meshes


@dataclass(frozen=True)
class DamagedMesh:
    """A mesh with CAD-like defects, and where they are."""

    mesh: Mesh
    centres: Tensor
    """Float[Tensor, "k 3"]: centre of each damaged region."""
    radii: Tensor
    """Float[Tensor, "k"]: each region's radius; away from every ball the surface is the clean one."""

    def away(self, points: Tensor, factor: float = 2.0) -> Tensor:
        """Bool[Tensor, "n"]: points farther than `factor` radii from every damaged region."""
        if len(self.radii) == 0:
            return torch.ones(len(points), dtype=torch.bool, device=points.device)
        distance = torch.cdist(points.double(), self.centres.double().to(points.device))
        return (distance > factor * self.radii.double().to(points.device)).all(1)


def _region(vertices: Tensor, faces: Tensor, centre: Tensor, radius: float) -> Tensor:
    """Bool[Tensor, "f"]: faces with a corner within `radius` of `centre`."""
    return ((vertices[faces] - centre).norm(dim=-1) < radius).any(1)


def damage_mesh(mesh: Mesh, *, holes: int = 3, duplicated: int = 2, inner: int = 2, flipped: float = 0.1,
                radius: float = 0.05, inset: float = 0.01, seed: int = 0) -> DamagedMesh:
    """A clean, closed mesh damaged as CAD meshes are, for testing signs against the clean mesh.

    - `holes` balls of `radius` (a fraction of the longest side) whose faces are deleted (open boundaries);
    - `duplicated` regions copied as a separate, coincident sheet, half of them facing the other way;
    - `inner` regions copied `inset` (a fraction of the longest side) inside along the vertex normals,
      as a separate sheet facing either way (internal faces); keep `inset` below half the thinnest wall;
    - a fraction `flipped` of all faces (sheets included) reversed one by one.

    Only holes and inner sheets change the surface; the returned regions cover holes, duplicated and
    inner sheets (reversed faces are everywhere and `orient_outward` repairs them).
    """
    if mesh.is_empty:
        raise InputError("damage_mesh needs a mesh with faces, got an empty mesh")
    if not (0 <= flipped <= 1 and radius > 0 and inset >= 0):
        raise ConfigError(f"damage_mesh needs 0 <= flipped <= 1, radius > 0 and inset >= 0, got flipped={flipped}, "
                          f"radius={radius}, inset={inset}")
    generator = torch.Generator().manual_seed(seed)
    vertices = mesh.vertices.detach().cpu().double()
    faces = mesh.faces.cpu().clone()
    extent = float((vertices.max(0).values - vertices.min(0).values).max())
    r = radius * extent
    normals = torch.from_numpy(vertex_normals(vertices.numpy(), faces.numpy()))
    centres = vertices[torch.randint(len(vertices), (holes + duplicated + inner,), generator=generator)]
    keep = torch.ones(len(faces), dtype=torch.bool)
    for centre in centres[:holes]:
        keep &= ~_region(vertices, faces, centre, r)
    out_vertices, out_faces, offset = [vertices], [faces[keep]], len(vertices)
    for i, centre in enumerate(centres[holes:]):
        used, local = torch.unique(faces[_region(vertices, faces, centre, r)], return_inverse=True)
        sheet = local.reshape(-1, 3) + offset
        if i < duplicated:  # coincident copy, every other one facing inward
            out_vertices.append(vertices[used])
            reverse = i % 2 == 1
        else:  # inner sheet: moved inside along the normals, facing either way
            out_vertices.append(vertices[used] - inset * extent * normals[used])
            reverse = bool(torch.rand(1, generator=generator) < 0.5)
        out_faces.append(sheet.flip(1) if reverse else sheet)
        offset += len(used)
    faces = torch.cat(out_faces)
    turn = torch.rand(len(faces), generator=generator) < flipped
    faces[turn] = faces[turn].flip(1)
    damaged = Mesh(torch.cat(out_vertices).to(mesh.vertices), faces.to(mesh.faces.device))
    return DamagedMesh(damaged, centres.to(mesh.vertices), torch.full((len(centres),), r).to(mesh.vertices))
