"""A mesh moved onto the points it was fitted to: the detail that a grid's cells are too wide to hold.

A field on a grid (the point fit's start: 256 cells a side) cannot bend between its grid points; a cloud whose points
lie closer together than the grid's cells can. `snap_to_points` subdivides the mesh once and moves each vertex along
the points' normal onto their implicit moving-least-squares surface (`plane_offsets`), the move averaged with the
mesh's neighbours (`ring_mean`) as many rounds as points held out of it ask for: where the points are exact the whole
move, where they are noisy or out of register a smooth one, and none unless the held-out points come `GAIN` closer.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator

import torch
from torch import Tensor

from neuralsurf.errors import ConfigError
from neuralsurf.geometry import closest_on_mesh, cloud_spacing, knn, local_origin, take_rows
from neuralsurf.sampling import held_out_split
from neuralsurf.structures import Mesh, PointCloud

log = logging.getLogger("neuralsurf")

NEIGHBOURS = 8
"""Points whose tangent planes make a vertex's moving-least-squares surface (Gaussian weights, one spacing wide)."""

ROUNDS = (0, 1, 2, 4, 8, 16, 32, 64)
"""The smoothing rounds tried, in order, until the held-out points stop coming closer."""

GAIN = 0.01
"""The least share by which the held-out points must come closer for the mesh to move (as `training.EarlyStop`'s)."""

SCORED = 50_000
"""Held-out points read at most (the first ones): the scores' memory stays bounded."""

CHUNK = 1 << 21
"""Vertices whose planes are read at once (about 300 bytes each): the memory stays bounded on large meshes."""


def subdivided(mesh: Mesh) -> Mesh:
    """`mesh` with each face split into four at its edges' midpoints (the same surface). Child j of face i is face
    i + j * len(mesh.faces): the corners' three, then the middle one."""
    faces, count = mesh.faces, len(mesh.vertices)
    ends = torch.cat([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]).sort(1).values
    edges, which = torch.unique(ends[:, 0] * count + ends[:, 1], return_inverse=True)
    ab, bc, ca = (count + which).reshape(3, -1)
    a, b, c = faces.T
    children = torch.cat([torch.stack(f, -1) for f in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])
    middle = lambda values: (values[edges // count] + values[edges % count]) / 2
    colors = None if mesh.vertex_colors is None else torch.cat([mesh.vertex_colors, middle(mesh.vertex_colors)])
    return Mesh(torch.cat([mesh.vertices, middle(mesh.vertices)]), children, colors)


def plane_offsets(vertices: Tensor, points: Tensor, normals: Tensor, spacing: float) -> tuple[Tensor, Tensor]:
    """(Float[Tensor, "v"] offsets, Float[Tensor, "v 3"] directions): each of Float[Tensor, "v 3"] `vertices` lies
    `offset` along `direction` from the points' implicit moving-least-squares surface (the tangent planes of its
    `NEIGHBOURS` nearest Float[Tensor, "n 3"] `points`, unit `normals`, weighted by a Gaussian one `spacing` wide;
    the direction is their weighted normal). A vertex farther than two spacings from every point gets 0. Read
    `CHUNK` vertices at a time."""
    if len(vertices) > CHUNK:
        parts = [plane_offsets(part, points, normals, spacing) for part in vertices.split(CHUNK)]
        return torch.cat([offset for offset, _ in parts]), torch.cat([direction for _, direction in parts])
    distance, index = knn(vertices, points, min(NEIGHBOURS, len(points)))
    weight = torch.softmax(-(distance / spacing) ** 2, -1)
    centre = points.mean(0)  # n . (v - p) as n . (v - centre) - n . (p - centre): no [v, k, 3] point gather
    heights = ((points - centre) * normals).sum(-1)
    normal = (weight[..., None] * take_rows(normals, index)).sum(1)
    offset = ((vertices - centre) * normal).sum(-1) - (weight * take_rows(heights, index)).sum(-1)
    return torch.where(distance[:, 0] < 2 * spacing, offset, 0.0), torch.nn.functional.normalize(normal, dim=-1)


def ring_mean(values: Tensor, faces: Tensor, incident: Tensor) -> Tensor:
    """Float[Tensor, "v"]: the mean over each vertex's faces (`incident` of them, `faces.reshape(-1).bincount()`)
    of their corners' mean of Float[Tensor, "v"] `values`: the vertex and its ring of neighbours."""
    corners = values[faces].mean(1)[:, None].expand(-1, 3).reshape(-1)
    return torch.zeros_like(values).index_add_(0, faces.reshape(-1), corners) / incident


def footprints(query: Tensor, mesh: Mesh) -> tuple[Tensor, Tensor, Tensor]:
    """Where Float[Tensor, "q 3"] `query` points lie over `subdivided(mesh)`: (Long[Tensor, "q"] the child face
    under each (of the face of `mesh` nearest it), Float[Tensor, "q 3"] the barycentric weights of its projection
    onto that face's plane, clamped into it, Float[Tensor, "q 3"] the face's unit normal)."""
    face = closest_on_mesh(query, mesh)[1]
    a, b, c = mesh.vertices.double()[mesh.faces[face]].unbind(1)
    normal = torch.cross(b - a, c - a, dim=-1)
    ab, ac, aq = b - a, c - a, query.double() - a
    area = (normal * normal).sum(-1).clamp_min(1e-300)
    v = (torch.cross(aq, ac, dim=-1) * normal).sum(-1) / area
    w = (torch.cross(ab, aq, dim=-1) * normal).sum(-1) / area
    u, v, w = torch.stack([1 - v - w, v, w], -1).clamp_min(0).unbind(-1)
    u, v, w = (t / (u + v + w) for t in (u, v, w))
    child = torch.where(u >= 0.5, 0, torch.where(v >= 0.5, 1, torch.where(w >= 0.5, 2, 3)))
    weights = torch.stack([torch.stack(t, -1) for t in ((2 * u - 1, 2 * v, 2 * w), (2 * u, 2 * v - 1, 2 * w),
                                                         (2 * u, 2 * v, 2 * w - 1), (1 - 2 * w, 1 - 2 * u, 1 - 2 * v))])
    weights = weights[child, torch.arange(len(query), device=child.device)]  # in `subdivided`'s corner order
    return face + child * len(mesh.faces), weights.float(), torch.nn.functional.normalize(normal, dim=-1).float()


def smoothed_moves(fine: Mesh, points: Tensor, normals: Tensor, spacing: float) -> Iterator[tuple[int, Tensor]]:
    """(rounds, Float[Tensor, "v 3"] vertices) for each count of `ROUNDS` in turn: `fine`'s vertices moved by their
    `plane_offsets` onto Float[Tensor, "n 3"] `points` (unit `normals`), the offset averaged over each vertex's ring
    (`ring_mean`: half its own, half the ring's mean) that many rounds, by at most `spacing`."""
    offset, direction = plane_offsets(fine.vertices, points.float(), normals.float(), spacing)
    incident = fine.faces.reshape(-1).bincount(minlength=len(fine.vertices)).clamp_min(1)
    done = 0
    for rounds in ROUNDS:
        for _ in range(rounds - done):
            offset = (offset + ring_mean(offset, fine.faces, incident)) / 2
        done = rounds
        yield rounds, fine.vertices - offset.clamp(-spacing, spacing)[:, None] * direction


def snap_to_points(mesh: Mesh, points: Tensor, normals: Tensor, held_out: Tensor, spacing: float | None = None
                   ) -> tuple[Mesh, dict[str, float]]:
    """`mesh` subdivided once and moved onto Float[Tensor, "n 3"] `points` (unit `normals`, the same frame): each
    vertex by its `plane_offsets` averaged over its ring some rounds (`smoothed_moves`), by at most one point spacing
    (`spacing`; default `cloud_spacing(points)`). The rounds are `ROUNDS` in order until one brings Float[Tensor,
    "h 3"] `held_out` points (kept out of `points`) no closer than the one before, their distance being their mean
    height over the mesh where they stand (`footprints`: a rough surface would pass closer to scattered points); the
    best is kept if it brings them `GAIN` closer than `mesh`, else `mesh` is returned. Returns (mesh, what was
    measured: the held-out points' mean height before and after, and the rounds chosen, -1 for none)."""
    spacing = cloud_spacing(points) if spacing is None else spacing
    fine = subdivided(Mesh(mesh.vertices.float(), mesh.faces, mesh.vertex_colors))
    held_out = held_out[:SCORED].float()
    under, weights, normal = footprints(held_out, mesh)
    corners = fine.faces[under]

    def score(vertices: Tensor) -> float:  # the held-out points' mean height over the mesh, where they stand
        surface = (weights[..., None] * vertices[corners]).sum(1)
        return float(((held_out - surface) * normal).sum(-1).abs().double().mean())

    before = best = score(fine.vertices)
    chosen, vertices = -1, fine.vertices
    for rounds, moved in smoothed_moves(fine, points, normals, spacing):
        if (now := score(moved)) >= best and chosen >= 0:
            break
        if now < best:
            best, chosen, vertices = now, rounds, moved
    if chosen < 0 or best > (1 - GAIN) * before:
        return mesh, {"held_out_before": before, "held_out_after": before, "rounds": -1}
    return (Mesh(vertices.to(mesh.vertices.dtype), fine.faces, fine.vertex_colors),
            {"held_out_before": before, "held_out_after": best, "rounds": chosen})


def median_edge(mesh: Mesh) -> float:
    """The median length of a non-empty `mesh`'s edges (each face's three)."""
    edges = (mesh.vertices[mesh.faces[:, [1, 2, 0]]] - mesh.vertices[mesh.faces]).norm(dim=-1)
    return float(edges.median())


def snap_to_cloud(mesh: Mesh, cloud: PointCloud, share: float, seed: int = 0) -> Mesh:
    """`snap_to_points` of `mesh` onto a world-frame `cloud` with normals, `share` of its points held out
    (`sampling.held_out_split` with `seed`: a point fit's own held-out points when its share and seed are these),
    where the points lie closer together than the mesh's edges (`median_edge`); else `mesh`, saying why.
    Computed in float32 about the cloud's `local_origin`."""
    if not 0 < share < 0.5:
        raise ConfigError(f"onto_points is the share of the points held out to choose the move, in (0, 0.5); got "
                          f"{share!r} (0 or null: the mesh as extracted)")
    held, kept = held_out_split(len(cloud), share, seed)
    movable = cloud.normals is not None and not mesh.is_empty and len(held) > 0 and len(kept) > 1
    if movable:
        edge = median_edge(mesh)
        origin = local_origin(cloud.points, edge)  # float32 from here, about it
        points = (cloud.points.double() - origin if origin.any() else cloud.points).to(mesh.vertices.device).float()
        movable = (spacing := cloud_spacing(points[kept])) < edge
    if not movable:
        log.info("mesh not moved onto the points: %s", "the cloud has no normals" if cloud.normals is None else
                 "the points lie no closer together than the mesh's vertices")
        return mesh
    normals = torch.nn.functional.normalize(cloud.normals.to(points), dim=-1)
    origin = origin.to(mesh.vertices.device)
    local = Mesh((mesh.vertices.double() - origin).float(), mesh.faces, mesh.vertex_colors)
    snapped, measured = snap_to_points(local, points[kept], normals[kept], points[held], spacing)
    if measured["rounds"] < 0:
        log.info("mesh not moved onto the points: the held-out points (%.4g from it) would not come %g %% closer",
                 measured["held_out_before"], 100 * GAIN)
        return mesh
    log.info("mesh moved onto the points: held-out points %.4g -> %.4g from it (%d smoothing rounds)",
             measured["held_out_before"], measured["held_out_after"], measured["rounds"])
    return Mesh((snapped.vertices.double() + origin).to(mesh.vertices.dtype), snapped.faces, snapped.vertex_colors)
