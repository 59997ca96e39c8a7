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


_EDGE_START = torch.tensor([_CORNERS[a] for a, _ in _EDGES])  # [12, 3] first corner of each edge
_EDGE_AXIS = torch.tensor([(b - a).bit_length() - 1 for a, b in _EDGES])  # [12]


def cube_triangles(values: Tensor, valid: Tensor | None, origins: Tensor, shape, level: float = 0.0) -> tuple[Tensor, Tensor]:
    """The level set's triangles inside some cubes of one grid, each corner named by its grid edge.

    Args: values Float[Tensor, "m X Y Z"] point values of m cubes; valid Bool[Tensor, "m X Y Z"] | None:
    points with a value (a cell with an invalid corner gets no triangles); origins Int64[Tensor, "m 3"]
    grid index of each cube's first point; shape: points per axis of the whole grid.
    Returns keys Int64[Tensor, "f 3"]: each triangle corner's grid edge (linear index of its first point
    * 3 + axis; triangles oriented towards values above `level`), and positions Float[Tensor, "f 3 3"]
    of those vertices in grid units (linear interpolation along the edge). Cubes that share points
    give their shared edges the same keys and positions (`merge_edge_vertices` joins them).
    """
    m, X, Y, Z = values.shape
    below = values < level
    case = torch.zeros((m, X - 1, Y - 1, Z - 1), dtype=torch.uint8, device=values.device)  # a byte a cell
    for c, (i, j, k) in enumerate(_CORNERS):
        case |= below[:, i : X - 1 + i, j : Y - 1 + j, k : Z - 1 + k].to(torch.uint8) << c
    crossed = (case > 0) & (case < 255)
    if valid is not None:
        for i, j, k in _CORNERS:
            crossed &= valid[:, i : X - 1 + i, j : Y - 1 + j, k : Z - 1 + k]
    cells = crossed.nonzero()  # [n, 4]: cube, cell
    table, counts = case_table(str(values.device))
    cell_case = case[tuple(cells.T)].long()
    keep = torch.arange(5, device=values.device) < counts[cell_case, None]  # [n, 5]
    edges = table[cell_case][keep]  # [f, 3] cell-local edges
    owner = cells[:, None, :].expand(-1, 5, -1)[keep]  # [f, 4] cube and cell of each triangle
    axis = _EDGE_AXIS.to(values.device)[edges]  # [f, 3]
    start = owner[:, None, 1:] + _EDGE_START.to(values.device)[edges]  # [f, 3, 3] first point in its cube
    linear = lambda p: ((owner[:, None, 0] * X + p[..., 0]) * Y + p[..., 1]) * Z + p[..., 2]
    step = torch.nn.functional.one_hot(axis, 3)
    flat = values.reshape(-1)
    v0, v1 = flat[linear(start)], flat[linear(start + step)]
    t = ((level - v0) / (v1 - v0)).clamp(0, 1)
    point = origins[owner[:, 0]][:, None, :] + start  # [f, 3, 3] in the grid
    keys = ((point[..., 0] * shape[1] + point[..., 1]) * shape[2] + point[..., 2]) * 3 + axis
    return keys, point.to(values.dtype) + t[..., None] * step.to(values.dtype)


def merge_edge_vertices(keys: Tensor, positions: Tensor) -> tuple[Tensor, Tensor]:
    """`cube_triangles`' keys Int64[Tensor, "f 3"] and positions Float[Tensor, "f 3 3"] -> vertices
    Float[Tensor, "v 3"] (one per grid edge) and faces Int64[Tensor, "f 3"]."""
    keys = keys.reshape(-1)
    if len(keys) and int(keys.max()) < 2**31:  # int32 sorts about twice as fast
        keys = keys.int()
    unique, faces = torch.unique(keys, return_inverse=True)
    vertices = positions.new_empty(len(unique), 3)
    vertices[faces] = positions.reshape(-1, 3)  # a shared edge's copies are equal
    return vertices, faces.reshape(-1, 3)


def marching_cubes_torch(values: Tensor, level: float = 0.0) -> tuple[Tensor, Tensor]:
    """Level set of Float[Tensor, "X Y Z"] point values, on their device.

    Returns vertices Float[Tensor, "v 3"] in grid units and faces Int[Tensor, "f 3"], oriented towards
    values above `level` (outward for an SDF), shared vertices merged.
    """
    origin = torch.zeros(1, 3, dtype=torch.long, device=values.device)
    return merge_edge_vertices(*cube_triangles(values[None], None, origin, values.shape, level))
