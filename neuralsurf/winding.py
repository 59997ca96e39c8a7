"""Inside and outside of imperfect triangle meshes: generalised winding numbers (Jacobson et al. 2013).

Real CAD meshes are rarely watertight: open boundaries, duplicated or inner sheets, overlapping
closed parts and flipped faces. Ray parity (`geometry.mesh_contains`) breaks on all of them; the
winding number `w(q) = sum_t Omega_t(q) / (4 pi)`, the signed solid angles of the triangles seen from
`q`, is 1 inside and 0 outside a closed, outward surface, varies smoothly across holes, and counts
overlapping parts and coincident sheets as 2 (still inside at the threshold 1/2).

- `winding_number(query, mesh)` through `MeshWinding`: the mesh's border loops (`border_edges`) closed
  by cones make a closed surface, whose winding number is an integer read from signed ray crossings
  (Open3D); the mesh's is that integer less the cones' solid angles, summed exactly wherever a
  rigorous bound says they can matter (within `tolerance` of the exact sum; `inside` exact wherever
  the side could change). `approximate=False` sums every triangle's solid angle.
- `orient_outward(mesh)`: faces made consistent across manifold edges, each connected patch then
  turned to face where more random rays escape to infinity (visibility, as Takayama et al. 2014):
  repairs flipped faces and inward patches, which the winding number needs.
- `signed_distance(points, mesh)` (unsigned distance to the triangles, sign from the winding number)
  and `inside(points, mesh)`; `boundary_faces(mesh)`: the faces between inside and outside (inner
  and stray sheets left out), the surface a shape's distances and samples should come from.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from neuralsurf.errors import ConfigError, InputError
from neuralsurf.geometry import point_to_mesh_distance
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


RAY_DIRECTIONS = torch.nn.functional.normalize(torch.tensor(
    [[0.5377, 0.6241, 0.5668], [-0.7289, 0.2173, 0.6493], [0.1559, -0.8917, 0.4249]], dtype=torch.float64), dim=-1)
"""Float64[Tensor, "3 3"]: the directions of the rays that count crossings: generic (none along an
axis or a diagonal of a grid, where marching-cubes vertices and faces line up)."""


def _mix(words: np.ndarray) -> np.ndarray:
    """UInt64[..., k] -> UInt64[...]: a hash of the last axis's values (equal rows, equal hashes;
    distinct rows collide with probability about 2^-64)."""
    h = np.full(words.shape[:-1], 0xCBF29CE484222325, dtype=np.uint64)
    with np.errstate(over="ignore"):
        for i in range(words.shape[-1]):
            h = (h ^ words[..., i].astype(np.uint64)) * np.uint64(0x100000001B3)
            h ^= h >> np.uint64(29)
    return h


def _edge_keys(edges: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct undirected edges of Int[e, 2] edges as (Int[k, 2] sorted pairs, Int[e] index of each)."""
    pairs = np.sort(edges, axis=1).astype(np.int64)
    n = int(pairs.max()) + 1 if len(pairs) else 1
    keys, index = np.unique(pairs[:, 0] * n + pairs[:, 1], return_inverse=True)
    return np.stack([keys // n, keys % n], 1), index.ravel()


def border_edges(faces: Tensor) -> Tensor:
    """The algebraic border of oriented triangles: each edge run more often one way than the other by
    the faces (Int[Tensor, "f 3"]), in the direction the faces run it, repeated by the difference.

    An edge between two consistent faces is no border; an open boundary is, and so is an edge between
    two faces that disagree (a flipped face: twice) or one of three faces. Every vertex has as many
    border edges in as out: they form closed loops, whatever the mesh.

    Returns:
        Int[Tensor, "b 2"] directed edges (a, b).
    """
    f = faces.cpu().numpy()
    directed = np.stack([f, np.roll(f, -1, axis=1)], -1).reshape(-1, 2)
    keys, edge = _edge_keys(directed)
    sense = np.where(directed[:, 0] < directed[:, 1], 1, -1)
    net = np.bincount(edge.ravel(), weights=sense, minlength=len(keys)).round().astype(np.int64)
    border = net != 0
    edges = np.where((net > 0)[:, None], keys, keys[:, ::-1])[border]
    return torch.from_numpy(np.repeat(edges, np.abs(net[border]), axis=0)).long()


@dataclass(frozen=True)
class _Caps:
    """Cones over the border loops of a mesh: with them the mesh is a closed surface (a 2-cycle)."""

    triangles: Tensor
    """Float64[Tensor, "h 3 3"]: (apex, b, a) for each border edge (a, b), grouped by cap."""
    first: Tensor
    """Int[Tensor, "k + 1"]: cap k's triangles are `triangles[first[k]:first[k + 1]]`."""
    centre: Tensor
    """Float64[Tensor, "k 3"]: each cap's apex, the mean of its loop's vertices."""
    radius: Tensor
    """Float64[Tensor, "k"]: the largest distance from the apex to a vertex of the loop: the cap
    lies in that ball."""
    area: Tensor
    """Float64[Tensor, "k"]: each cap's area."""


def _caps(vertices: Tensor, faces: Tensor) -> _Caps:
    """One cone a connected set of border loops (`border_edges`), from Float64[Tensor, "v 3"]
    vertices and Int[Tensor, "f 3"] faces."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    edges = border_edges(faces)
    if len(edges) == 0:
        empty = vertices.new_zeros(0)
        return _Caps(vertices.new_zeros(0, 3, 3), torch.zeros(1, dtype=torch.long), vertices.new_zeros(0, 3),
                     empty, empty)
    used, local = torch.unique(edges, return_inverse=True)
    e = local.numpy()
    graph = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(len(used), len(used)))
    k, label = connected_components(graph, directed=False)
    label = torch.from_numpy(label).long()
    points = vertices[used]
    count = torch.bincount(label, minlength=k).double()
    centre = points.new_zeros(k, 3).index_add_(0, label, points) / count[:, None]
    radius = points.new_zeros(k).scatter_reduce_(0, label, (points - centre[label]).norm(dim=-1), "amax")
    cap = label[local[:, 0]]
    order = torch.argsort(cap, stable=True)
    a, b = vertices[edges[order, 0]], vertices[edges[order, 1]]
    apex = centre[cap[order]]
    triangles = torch.stack([apex, b, a], 1)
    area = 0.5 * torch.linalg.cross(b - apex, a - apex).norm(dim=-1)
    sizes = torch.bincount(cap, minlength=k)
    return _Caps(triangles, torch.cat([sizes.new_zeros(1), sizes.cumsum(0)]), centre, radius,
                 points.new_zeros(k).index_add_(0, cap[order], area))


class MeshWinding:
    """A mesh prepared for exact generalised winding numbers at many points.

    The mesh's border loops (`border_edges`) are closed by cones (caps H), which makes the mesh plus
    H a closed surface: its winding number is an integer, the signed count of its faces that any ray
    from the point crosses (+1 leaving through a face's front), read by Open3D's ray casting. The
    mesh's own winding number is that integer less the caps' sum of solid angles: exact near the caps,
    and neglected where a rigorous bound (a cap of area A within a ball of radius r about its apex,
    seen from distance D > r, subtends at most A / (D - r)^2 / (4 pi)) keeps the total neglected below
    the tolerance. A closed mesh has no caps: its winding number is the crossing count. Crossings are
    counted along two generic rays; where they disagree (a ray through an edge) a third decides.
    """

    def __init__(self, mesh: Mesh):
        if mesh.is_empty:
            raise InputError("winding numbers need a mesh with faces, got an empty mesh")
        vertices = mesh.vertices.detach().cpu().double()
        low, high = vertices.min(0).values, vertices.max(0).values
        self.centre, self.extent = (low + high) / 2, float((high - low).max().clamp_min(1e-12))
        # solid angles are invariant to translation and scale: work in the mesh's unit box
        self.vertices = (vertices - self.centre) / self.extent
        faces = mesh.faces.cpu()
        faces = faces[(faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 2] != faces[:, 0])]
        self.faces = faces
        self.caps = _caps(self.vertices, faces)
        self._scenes: dict[int, tuple] = {}

    @property
    def closed(self) -> bool:
        """Whether the mesh has no border (its winding number is an integer everywhere)."""
        return len(self.caps.triangles) == 0

    def unit(self, points: Tensor) -> Tensor:
        """Float64[Tensor, "m 3"]: points in the mesh's unit box."""
        return (points.detach().cpu().double() - self.centre) / self.extent

    def _scenes_along(self, k: int) -> list[tuple]:
        """(Open3D scene, sign): the closed surface's triangles facing along RAY_DIRECTIONS[k] (+1) and
        against it (-1). Open3D counts hits at the same distance once (a ray through an edge crosses
        once), so coincident copies of a triangle go to scenes of their own, one a copy."""
        import open3d as o3d

        if k not in self._scenes:
            triangles = torch.cat([self.vertices[self.faces], self.caps.triangles]).float()
            normal = torch.linalg.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
            facing = torch.sign(normal.double() @ RAY_DIRECTIONS[k]).long()
            _, copy = np.unique(_mix(np.sort(_mix(triangles.numpy().view(np.uint32)), axis=1)), return_inverse=True)
            order = np.argsort(copy.ravel(), kind="stable")
            first = np.searchsorted(copy.ravel()[order], copy.ravel()[order])
            layer = np.empty(len(order), np.int64)
            layer[order] = np.arange(len(order)) - first  # 0 for the first copy, 1 for the second, ...
            scenes = []
            for sign in (1, -1):
                for level in range(int(layer.max()) + 1 if len(layer) else 0):
                    chosen = (facing == sign) & torch.from_numpy(layer == level)
                    if chosen.any():
                        scene = o3d.t.geometry.RaycastingScene()
                        points = triangles[chosen].reshape(-1, 3).numpy()
                        scene.add_triangles(o3d.core.Tensor(points),
                                            o3d.core.Tensor(np.arange(len(points), dtype=np.uint32).reshape(-1, 3)))
                        scenes.append((scene, sign))
            self._scenes[k] = scenes
        return self._scenes[k]

    def _crossings(self, points: Tensor, k: int) -> Tensor:
        """Int[Tensor, "m"]: signed crossings of the closed surface by rays from Float64[Tensor, "m 3"]
        unit-box points along RAY_DIRECTIONS[k]."""
        import open3d as o3d

        rays = o3d.core.Tensor(torch.cat([points, RAY_DIRECTIONS[k].expand(len(points), 3)], 1).float().numpy())
        count = torch.zeros(len(points), dtype=torch.long)
        for scene, sign in self._scenes_along(k):
            count += sign * torch.from_numpy(scene.count_intersections(rays).numpy()).long()
        return count

    def closed_winding(self, points: Tensor) -> Tensor:
        """Int[Tensor, "m"]: the winding number of the mesh plus its caps at unit-box points."""
        first, second = self._crossings(points, 0), self._crossings(points, 1)
        differ = torch.nonzero(first != second).squeeze(1)
        if len(differ):
            third = self._crossings(points[differ], 2)
            first[differ] = torch.stack([first[differ], second[differ], third], 1).median(1).values
        return first

    def cap_winding(self, points: Tensor, tolerance: float, elements: int = 2**20) -> Tensor:
        """Float64[Tensor, "m"]: the caps' winding number at Float64[Tensor, "m 3"] unit-box points,
        each cap summed exactly unless the bounds of the caps left out add up to at most `tolerance`."""
        caps, out = self.caps, points.new_zeros(len(points))
        if self.closed or len(points) == 0:
            return out
        rows, pairs = max(1, elements // len(caps.radius)), []
        for start in range(0, len(points), rows):
            gap = torch.cdist(points[start:start + rows], caps.centre) - caps.radius
            bound = torch.where(gap > 0, caps.area / (4 * math.pi * gap.clamp_min(1e-300) ** 2), math.inf)
            ascending, order = bound.sort(1)
            left_out = torch.zeros_like(bound, dtype=torch.bool).scatter_(1, order, ascending.cumsum(1) <= tolerance)
            query, cap = torch.nonzero(~left_out, as_tuple=True)
            pairs.append(torch.stack([cap, query + start]))
        cap, query = torch.cat(pairs, 1)[:, torch.argsort(torch.cat(pairs, 1)[0], stable=True)]
        triangles, unit = caps.triangles.float(), points.float()
        present, count = torch.unique_consecutive(cap, return_counts=True)
        for k, rows_k in zip(present.tolist(), query.split(count.tolist())):
            part = triangles[caps.first[k]:caps.first[k + 1]]
            out[rows_k] += _exact(unit[rows_k], part, elements).double()
        return out

    def __call__(self, query: Tensor, tolerance: float = 1e-2) -> Tensor:
        """Float64[Tensor, "m"]: the winding number at Float[Tensor, "m 3"] points (the mesh's frame),
        within `tolerance` of the exact sum (float rounding aside)."""
        points = self.unit(query)
        return self.closed_winding(points).double() - self.cap_winding(points, tolerance)

    def inside(self, query: Tensor, tolerance: float = 0.25) -> Tensor:
        """Bool[Tensor, "m"]: winding number at least 1/2, certain: points whose value within
        `tolerance` lies within `tolerance` of 1/2 are summed again with every cap exact."""
        return self.certain(query, self(query, tolerance), tolerance) >= INSIDE_THRESHOLD

    def certain(self, query: Tensor, values: Tensor, tolerance: float) -> Tensor:
        """`values` (within `tolerance`) with those within `tolerance` of 1/2 made exact."""
        unsure = torch.nonzero((values - INSIDE_THRESHOLD).abs() <= tolerance).squeeze(1)
        if len(unsure) and not self.closed:
            values = values.clone()
            values[unsure] = self(query[unsure], 0.0)
        return values


def winding_number(query: Tensor, mesh: Mesh, *, approximate: bool = True, tolerance: float = 1e-2,
                   elements: int = 2**20) -> Tensor:
    """Generalised winding number of a triangle mesh at each query point.

    About 1 inside and 0 outside a closed surface with outward (counter-clockwise) faces; across a
    hole it varies smoothly, overlapping closed parts count 2. With `approximate`, `MeshWinding`:
    an integer read from ray crossings of the mesh closed by caps over its holes, less the caps'
    solid angles, within `tolerance` of the exact sum (exact for a closed mesh); otherwise every
    triangle's solid angle summed exactly (float32, in the mesh's unit box).

    Args:
        query: Float[Tensor, "m 3"]; mesh: Mesh in the same frame.
        elements: query-triangle pairs per chunk (memory: about 200 bytes each).
    Returns:
        Float[Tensor, "m"] on the query's device, in its dtype.
    """
    _check(query, mesh, "winding_number")
    if not tolerance >= 0:
        raise ConfigError(f"winding_number: tolerance must be >= 0, got {tolerance}")
    if approximate:
        return MeshWinding(mesh)(query, tolerance).to(query)
    winding = MeshWinding(mesh)
    triangles = winding.vertices[winding.faces].float()
    return _exact(winding.unit(query).float(), triangles, elements).to(query)


def inside(points: Tensor, mesh: Mesh, *, approximate: bool = True) -> Tensor:
    """Bool[Tensor, "n"]: points whose winding number is at least 1/2: with `approximate`,
    `MeshWinding.inside` (certain: exact wherever the bounded part could change the side), otherwise
    the exact sum over every triangle."""
    _check(points, mesh, "inside")
    if approximate:
        return MeshWinding(mesh).inside(points).to(points.device)
    return winding_number(points, mesh, approximate=False) >= INSIDE_THRESHOLD


def signed_distance(points: Tensor, mesh: Mesh, *, approximate: bool = True) -> Tensor:
    """Float[Tensor, "n"]: the exact distance to the mesh's triangles, negative where the winding
    number says inside (`inside`). Right for open, multi-sheet meshes whose faces face outward (run
    `orient_outward` first when they may not)."""

    _check(points, mesh, "signed_distance")
    distance = point_to_mesh_distance(points, mesh)
    return torch.where(inside(points, mesh, approximate=approximate).to(distance.device), -distance, distance)


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


def boundary_faces(mesh: Mesh, offset: float = 1e-3) -> Tensor:
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
    tolerance = 0.05  # the scores' thresholds are 1/4 from 1/2; sides near 1/2 are made exact below
    winding = MeshWinding(Mesh(vertices, faces))
    wind = winding(sides, tolerance)
    active = torch.ones(patches, dtype=torch.bool)
    while True:
        front, back = wind.chunk(2)
        kept = active[patch]
        score = _weighted_median((front + back)[kept] / 2, area[kept], patch[kept], patches)
        sheet = active & candidate & ((score >= 0.75) | (score < 0.25))
        if not sheet.any():
            break
        active &= ~sheet
        if not active.any():
            return torch.zeros(len(faces), dtype=torch.bool, device=mesh.faces.device)
        # the winding number of the faces left
        winding = MeshWinding(Mesh(vertices, faces[active[patch]]))
        wind = winding(sides, tolerance)
    front, back = winding.certain(sides, wind, tolerance).chunk(2)
    return (active[patch] & ((front >= INSIDE_THRESHOLD) != (back >= INSIDE_THRESHOLD))).to(mesh.faces.device)


def _border_faces(faces: Tensor) -> Tensor:
    """Bool[Tensor, "f"]: faces with an edge no other face has (Int[Tensor, "f 3"] faces)."""
    f = faces.numpy()
    _, edge = _edge_keys(np.stack([f, np.roll(f, -1, axis=1)], -1).reshape(-1, 2))
    return torch.from_numpy((np.bincount(edge)[edge] == 1).reshape(-1, 3).any(1))


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
    _, edge = _edge_keys(directed)
    count = np.bincount(edge)
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


