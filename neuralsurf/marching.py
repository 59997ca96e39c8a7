"""Marching cubes in PyTorch, for grids that live on a GPU.

The case table is generated, not typed in: on each cube face the level set's segments are chosen
from that face's four corners alone (an ambiguous face keeps its two inside corners apart), so two
cells that share a face cut it alike and the mesh has no cracks; each cube's segments close into
loops, fanned into triangles. Vertices sit on grid edges by linear interpolation, as in skimage's
Lewiner marching cubes, so both give the same vertices; only ambiguous cells may be triangulated
differently. `neuralsurf.extract` uses it for fields evaluated on a GPU.
"""

from __future__ import annotations

import functools

import torch
from torch import Tensor

# corner c of a cell sits at offset (c & 1, c >> 1 & 1, c >> 2 & 1); edge e joins two corners that
# differ along one axis
_CORNERS = [(c & 1, c >> 1 & 1, c >> 2 & 1) for c in range(8)]
_EDGES = [(a, a | 1 << axis) for axis in range(3) for a in range(8) if not a >> axis & 1]
# faces as corner cycles, counter-clockwise seen from outside the cell
_FACES = [(0, 4, 6, 2), (1, 3, 7, 5), (0, 1, 5, 4), (2, 6, 7, 3), (0, 2, 3, 1), (4, 5, 7, 6)]
_EDGE_FACES = [{f for f, face in enumerate(_FACES) if set(edge) <= set(face)} for edge in _EDGES]  # two each


def _edge(a: int, b: int) -> int:
    return _EDGES.index((min(a, b), max(a, b)))


def _case_triangles(case: int) -> list[tuple[int, int, int]]:
    """Triangles (edge indices) of the cell whose corners c with bit c of `case` set lie below the level."""
    inside = [case >> c & 1 for c in range(8)]
    following = {}  # each crossed edge -> the next crossed edge along the level set's loop
    for face in _FACES:
        for i, corner in enumerate(face):
            if not inside[corner] or inside[face[i - 1]]:
                continue  # runs of inside corners are walked from their first corner, after an outside one
            j = i
            while inside[face[(j + 1) % 4]]:
                j += 1
            entry, exit_ = _edge(face[i - 1], corner), _edge(face[j % 4], face[(j + 1) % 4])
            following[exit_] = entry
    triangles = []
    while following:
        loop, edge = [], next(iter(following))
        while edge in following:
            loop.append(edge)
            edge = following.pop(edge)
        loop = _fan_start(loop)
        triangles += [(loop[0], loop[k + 1], loop[k]) for k in range(1, len(loop) - 1)]  # outward
    return triangles


def _fan_start(loop: list[int]) -> list[int]:
    """The loop rotated so that its fan's diagonals never join two edges of one cube face: the cell
    across that face could draw the same diagonal, and the mesh edge would have four triangles.
    (Every loop of the 256 cases has such a rotation.)"""
    for r in range(len(loop)):
        rotated = loop[r:] + loop[:r]
        if all(not _EDGE_FACES[rotated[0]] & _EDGE_FACES[rotated[k]] for k in range(2, len(loop) - 1)):
            return rotated
    raise AssertionError(f"no fan without a face diagonal for loop {loop}")


@functools.lru_cache(maxsize=None)
def case_table(device: str = "cpu") -> tuple[Tensor, Tensor]:
    """Int[Tensor, "256 5 3"] edge indices of each case's triangles (-1 padded) and Int[Tensor, "256"] their
    counts."""
    cases = [_case_triangles(case) for case in range(256)]
    table = torch.full((256, 5, 3), -1, dtype=torch.long)
    for case, triangles in enumerate(cases):
        if triangles:
            table[case, : len(triangles)] = torch.tensor(triangles)
    return table.to(device), torch.tensor([len(t) for t in cases]).to(device)


def marching_cubes_torch(values: Tensor, level: float = 0.0) -> tuple[Tensor, Tensor]:
    """Level set of Float[Tensor, "X Y Z"] point values, on their device.

    Returns vertices Float[Tensor, "v 3"] in grid units and faces Int[Tensor, "f 3"], oriented towards
    values above `level` (outward for an SDF), shared vertices merged.
    """
    X, Y, Z = values.shape
    below = values < level
    case = torch.zeros((X - 1, Y - 1, Z - 1), dtype=torch.uint8, device=values.device)  # a byte a cell
    for c, (i, j, k) in enumerate(_CORNERS):
        case |= below[i : X - 1 + i, j : Y - 1 + j, k : Z - 1 + k].to(torch.uint8) << c
    cells = ((case > 0) & (case < 255)).nonzero()  # [n, 3]
    table, counts = case_table(str(values.device))
    cell_case = case[cells[:, 0], cells[:, 1], cells[:, 2]].long()
    triangles = table[cell_case]  # [n, 5, 3]
    keep = torch.arange(5, device=values.device) < counts[cell_case, None]  # [n, 5]
    edges = triangles[keep]  # [f, 3] cell-local edges
    owner = cells[:, None, :].expand(-1, 5, -1)[keep]  # [f, 3] cell of each triangle
    edge_start = torch.tensor([_CORNERS[a] for a, _ in _EDGES], device=values.device)  # [12, 3]
    edge_axis = torch.tensor([(b - a).bit_length() - 1 for a, b in _EDGES], device=values.device)  # [12]
    start = owner[:, None, :] + edge_start[edges]  # [f, 3, 3] grid point where each vertex's edge starts
    key = ((start[..., 0] * Y + start[..., 1]) * Z + start[..., 2]) * 3 + edge_axis[edges]
    unique, faces = torch.unique(key.reshape(-1), return_inverse=True)
    axis, point = unique % 3, unique // 3
    p = torch.stack([point // (Y * Z), point // Z % Y, point % Z], -1)  # [v, 3]
    step = torch.nn.functional.one_hot(axis, 3)
    v0 = values[p[:, 0], p[:, 1], p[:, 2]]
    q = p + step
    v1 = values[q[:, 0], q[:, 1], q[:, 2]]
    t = ((level - v0) / (v1 - v0)).clamp(0, 1)
    vertices = p.to(values.dtype) + t[:, None] * step.to(values.dtype)
    return vertices, faces.reshape(-1, 3)
