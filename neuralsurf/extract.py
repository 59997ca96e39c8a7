"""Field -> Mesh: chunked, coarse-to-fine, block-wise marching cubes; slices of fields for TensorBoard.

A field is any callable mapping world points x[..., 3] (float32 tensor) to values f[...], negative
inside. `extract_mesh` samples it on a grid of cubic voxels covering the extraction box and runs
scikit-image's marching cubes (Lewiner) on it; the mesh comes back in the world frame with outward
(towards positive f) counter-clockwise faces.

How the pieces fit:

- `make_grid` picks the sample grid: `resolution` cells along the longest side of the box, the same
  spacing on every axis, centred on the box.
- Dense mode evaluates all (n+1)^3 grid points. Coarse-to-fine mode evaluates a coarse grid, then
  refines, level by level, only the cells that may contain the surface (`_needs_refinement`), and
  evaluates the fine grid only there.
- Either way marching cubes runs per block of `_BLOCK` cells that contains a sign change, and the
  blocks are welded through the grid edges their shared vertices lie on, so the mesh is the one a
  single dense marching-cubes call would give (see `_weld_units`).

Never imports neuralsurf.models or training.
"""

from __future__ import annotations

import functools
import itertools
import logging
import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor, nn

from neuralsurf.errors import ConfigError, ExtractionError, InputError
from neuralsurf.structures import Mesh

log = logging.getLogger(__name__)

Field = Callable[[Tensor], Tensor]

_BLOCK = 16
"""Marching cubes runs on blocks of _BLOCK^3 cells."""
_PAGE = 8
"""The sparse store keeps values in pages of _PAGE^3 grid points, allocated where needed."""
_CELLS_PER_BATCH = 16_384
"""Coarse-to-fine bookkeeping works on this many cells at a time, bounding its memory."""
_CORNERS = np.array(list(itertools.product((0, 1), repeat=3)), dtype=np.int64)
"""Int[ndarray, "8 3"]: corner offsets of a cell."""
_LATTICE = np.array(list(itertools.product((0, 1, 2), repeat=3)), dtype=np.int64)
"""Int[ndarray, "27 3"]: the 3x3x3 points spanned by the eight children of a cell, in child steps."""


# --------------------------------------------------------------------------------------- the grid


@dataclass(frozen=True)
class Grid:
    """A regular grid of cubic cells in the world frame: point (i, j, k) is origin + (i, j, k) * spacing."""

    origin: np.ndarray
    """Float[ndarray, "3"]: world position of grid point (0, 0, 0) (float64)."""
    spacing: float
    """World edge length of one cell."""
    cells: tuple[int, int, int]
    """Number of cells along x, y and z; the grid has cells + 1 points per axis."""

    @property
    def shape(self) -> tuple[int, int, int]:
        """Number of grid points along x, y and z."""
        return tuple(c + 1 for c in self.cells)

    def world(self, index: np.ndarray) -> np.ndarray:
        """Int[ndarray, "n 3"] grid indices -> Float[ndarray, "n 3"] float32 world points.

        The one place grid points become coordinates, so a point gets bit-identical input (and, for
        a deterministic field, value) whichever code path or chunk evaluates it.
        """
        return (self.origin + index * self.spacing).astype(np.float32)


def make_grid(bounds, resolution: int) -> Grid:
    """The marching-cubes grid for a (2, 3) box: `resolution` cells along its longest side.

    Every axis uses the same spacing (cubic voxels); the shorter axes get enough cells to cover
    the box and are centred on it, so the grid covers the box and overhangs it by less than one cell.
    """
    box = _as_bounds(bounds)
    if not (isinstance(resolution, (int, np.integer)) and resolution >= 2):
        raise ConfigError(
            f"resolution must be an integer >= 2 (cells along the longest side), got {resolution!r}"
        )
    extent = box[1] - box[0]
    spacing = float(extent.max()) / int(resolution)
    cells = np.maximum(1, np.ceil(extent / spacing - 1e-6)).astype(np.int64)
    cells[int(extent.argmax())] = int(resolution)
    origin = (box[0] + box[1]) / 2 - cells * spacing / 2
    return Grid(origin=origin, spacing=spacing, cells=tuple(int(c) for c in cells))


def _as_bounds(bounds) -> np.ndarray:
    """Array-like (2, 3) min/max corners -> Float[ndarray, "2 3"] float64, checked."""
    try:
        if isinstance(bounds, Tensor):
            box = bounds.detach().to("cpu", torch.float64).numpy()
        else:
            box = np.asarray(bounds, dtype=np.float64)
    except (TypeError, ValueError) as error:
        raise InputError(f"bounds must be a (2, 3) array of min and max corners: {error}") from None
    if box.shape != (2, 3):
        raise InputError(f"bounds must have shape (2, 3) (min corner, max corner), got {box.shape}")
    if not np.isfinite(box).all():
        raise InputError(f"bounds must be finite, got {box.tolist()}")
    if not (box[1] > box[0]).all():
        raise InputError(
            f"bounds must have max > min on every axis, got min {box[0].tolist()} max {box[1].tolist()}"
        )
    return box


def _resolve_bounds(field: Field, bounds) -> np.ndarray:
    """`bounds` if given, else `field.bounds`; Float[ndarray, "2 3"]."""
    if bounds is None:
        bounds = getattr(field, "bounds", None)
        if bounds is None:
            raise InputError(
                f"no extraction box: pass bounds=[[xmin, ymin, zmin], [xmax, ymax, zmax]] (world frame) "
                f"or give the field a (2, 3) `bounds` attribute; {type(field).__name__} has none"
            )
    return _as_bounds(bounds)


def _field_device(field: Field, device: torch.device | str | None) -> torch.device:
    """Where to evaluate: a module's parameters (or buffers) decide, else `device`, else CPU."""
    if isinstance(field, nn.Module):
        for tensor in itertools.chain(field.parameters(), field.buffers()):
            return tensor.device
    return torch.device(device) if device is not None else torch.device("cpu")


# ---------------------------------------------------------------------------------- evaluation


class _Sampler:
    """Evaluates a field at grid points in chunks, without gradients, counting evaluations."""

    def __init__(self, field: Field, grid: Grid, chunk_size: int, device: torch.device):
        if not (isinstance(chunk_size, (int, np.integer)) and chunk_size >= 1):
            raise ConfigError(
                f"chunk_size must be a positive integer (points per field call), got {chunk_size!r}"
            )
        self.field, self.grid, self.chunk_size, self.device = field, grid, int(chunk_size), device
        self.evaluations = 0
        self.low, self.high = math.inf, -math.inf

    def __call__(self, index: np.ndarray) -> np.ndarray:
        """Int[ndarray, "n 3"] grid indices -> Float[ndarray, "n"] float32 field values."""
        out = np.empty(len(index), dtype=np.float32)
        for start in range(0, len(index), self.chunk_size):
            out[start : start + self.chunk_size] = self._chunk(index[start : start + self.chunk_size])
        return out

    def dense(self) -> np.ndarray:
        """Float[ndarray, "X Y Z"] float32 values at every grid point (X, Y, Z = grid.shape)."""
        shape = self.grid.shape
        out = np.empty(int(np.prod(shape)), dtype=np.float32)
        for start in range(0, len(out), self.chunk_size):
            linear = np.arange(start, min(start + self.chunk_size, len(out)), dtype=np.int64)
            out[start : start + len(linear)] = self._chunk(np.stack(np.unravel_index(linear, shape), -1))
        return out.reshape(shape)

    def _chunk(self, index: np.ndarray) -> np.ndarray:
        points = self.grid.world(index)
        with torch.no_grad():
            values = self.field(torch.from_numpy(points).to(self.device))
        if not isinstance(values, Tensor) or values.numel() != len(points):
            shape = tuple(values.shape) if isinstance(values, Tensor) else type(values).__name__
            raise InputError(
                f"the field must map x[..., 3] to f[...]; for x of shape {tuple(points.shape)} it returned "
                f"{shape}; return one value per point"
            )
        values = values.detach().reshape(-1).to("cpu", torch.float32).numpy()
        self.evaluations += len(values)
        nan = np.isnan(values)
        if nan.any():
            where = points[np.argmax(nan)].tolist()
            raise ExtractionError(
                f"the field returned NaN at {int(nan.sum())} of {len(values)} points (e.g. at world "
                f"x={where}); fix the model (diverged training, 0/0, sqrt of a negative) or the inputs"
            )
        if len(values):
            self.low, self.high = min(self.low, float(values.min())), max(self.high, float(values.max()))
        return values


# ------------------------------------------------------------------------------ sparse storage


class _SparseValues:
    """Float32 values on a subset of grid points: a dense coarse lattice (`set_base`) plus
    _PAGE^3 pages allocated on first write, so memory follows the refined shell, not the grid.

    Unknown points read as NaN (the sampler rejects NaN field values, so NaN only means unknown).
    """

    def __init__(self, shape: tuple[int, int, int]):
        self.shape = shape
        self.table = np.full([-(-s // _PAGE) for s in shape], -1, dtype=np.int64)
        self.pages = np.empty((0, _PAGE, _PAGE, _PAGE), dtype=np.float32)
        self.used = 0
        self.base = np.empty((0, 0, 0), dtype=np.float32)
        self.base_maps = [np.full(s, -1, dtype=np.int64) for s in shape]

    def set_base(self, axes: list[np.ndarray], values: np.ndarray) -> None:
        """Store a lattice densely instead of in pages (the coarse grid: it touches every page).

        axes: per axis the grid coordinates of the lattice (Int[ndarray, "a"], "b", "c");
        values: Float[ndarray, "a b c"].
        """
        self.base = values.astype(np.float32)
        for lattice, mapping in zip(axes, self.base_maps):
            mapping[lattice] = np.arange(len(lattice))

    def _base_get(self, index: np.ndarray) -> np.ndarray:
        """Int[ndarray, "n 3"] -> Float[ndarray, "n"]: lattice values, NaN off the lattice."""
        where = [mapping[index[:, a]] for a, mapping in enumerate(self.base_maps)]
        on = (where[0] >= 0) & (where[1] >= 0) & (where[2] >= 0)
        out = np.full(len(index), np.nan, dtype=np.float32)
        out[on] = self.base[where[0][on], where[1][on], where[2][on]]
        return out

    def locate(self, index: np.ndarray, create: bool) -> tuple[np.ndarray, ...]:
        """Int[ndarray, "n 3"] grid points -> (page, i, j, k) addresses, each Int[ndarray, "n"];
        page is -1 for unallocated pages unless `create` allocates them."""
        blocks = tuple((index // _PAGE).T)
        page = self.table[blocks]
        if create and (page < 0).any():
            missing = np.unique(np.ravel_multi_index(blocks, self.table.shape)[page < 0])
            if self.used + len(missing) > len(self.pages):  # grow in place (realloc), not by copy
                old = len(self.pages)
                self.pages.resize((max(old * 5 // 4, self.used + len(missing)),) + self.pages.shape[1:],
                                  refcheck=False)
                self.pages[old:] = np.nan
            self.table.reshape(-1)[missing] = np.arange(self.used, self.used + len(missing))
            self.used += len(missing)
            page = self.table[blocks]
        offset = index % _PAGE
        return page, offset[:, 0], offset[:, 1], offset[:, 2]

    def get(self, index: np.ndarray) -> np.ndarray:
        """Int[ndarray, "n 3"] -> Float[ndarray, "n"]: stored values, NaN where unknown."""
        page, i, j, k = self.locate(index, create=False)
        out = self._base_get(index)
        have = (page >= 0) & np.isnan(out)
        out[have] = self.pages[page[have], i[have], j[have], k[have]]
        return out

    def fill(self, index: np.ndarray, evaluate: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
        """Values at Int[ndarray, "n 3"] points (repeats allowed): evaluates each unknown point once.

        Repeats are removed without sorting: every unknown entry writes its row number into the
        point's slot and the rows that read their own number back are the ones evaluated.
        """
        values = self._base_get(index)
        rest = np.flatnonzero(np.isnan(values))
        if not len(rest):
            return values
        address = self.locate(index[rest], create=True)
        paged = self.pages[address]
        unknown = np.flatnonzero(np.isnan(paged))
        if len(unknown):
            picked = tuple(a[unknown] for a in address)
            ids = np.arange(len(unknown), dtype=np.int32)
            self.pages.view(np.int32)[picked] = ids  # small non-negative ints: never NaN bit patterns
            first = unknown[self.pages.view(np.int32)[picked] == ids]
            self.pages[tuple(a[first] for a in address)] = evaluate(index[rest[first]])
            paged[unknown] = self.pages[picked]
        values[rest] = paged
        return values

    def box(self, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """Float[ndarray, "X Y Z"]: the values of grid points lo..hi (inclusive), NaN where unknown."""
        first, last = lo // _PAGE, hi // _PAGE + 1
        slots = self.table[first[0] : last[0], first[1] : last[1], first[2] : last[2]]
        tiles = self.pages[np.maximum(slots, 0)]  # (a, b, c, P, P, P)
        tiles[slots < 0] = np.nan
        a, b, c = slots.shape
        out = tiles.transpose(0, 3, 1, 4, 2, 5).reshape(a * _PAGE, b * _PAGE, c * _PAGE)
        start = lo - first * _PAGE
        stop = start + hi - lo + 1
        out = np.ascontiguousarray(out[start[0] : stop[0], start[1] : stop[1], start[2] : stop[2]])
        where = [mapping[a : b + 1] for mapping, a, b in zip(self.base_maps, lo, hi)]
        on = [np.flatnonzero(w >= 0) for w in where]
        if all(len(o) for o in on):
            out[np.ix_(*on)] = self.base[np.ix_(*[w[o] for w, o in zip(where, on)])]
        return out


# ------------------------------------------------------------------------- coarse-to-fine sampling


def _needs_refinement(corners: np.ndarray, level: float, threshold: float) -> np.ndarray:
    """Float[ndarray, "c 8"] corner values -> Bool[ndarray, "c"]: may the cell contain the level set?

    True when the corners straddle `level` (as marching cubes classifies them: f > level or not) or
    when some corner lies within `threshold` of it. With threshold >= L * diagonal / 2, a cell that
    is not refined holds no point at the level for any L-Lipschitz field: every point of a cube lies
    within diagonal / 2 of a corner, so |f(x) - level| >= min_c |f(c) - level| - L * diagonal / 2 > 0.
    """
    shifted = corners.astype(np.float64) - level
    outside = shifted > 0
    straddles = outside.any(1) & ~outside.all(1)
    return straddles | (np.abs(shifted).min(1) <= threshold)


_CHILD_CORNERS = np.ravel_multi_index(tuple((_CORNERS[:, None] + _CORNERS[None]).reshape(-1, 3).T), (3, 3, 3))
"""Int[ndarray, "64"]: for child c (row-major over the 8) and its corner k, the index into _LATTICE."""


def _coarse_to_fine(sampler: _Sampler, grid: Grid, level: float, margin: float, depth: int
                    ) -> tuple[_SparseValues, np.ndarray]:
    """Evaluate the field near the level set only.

    Evaluates a coarse grid of cells of 2^depth fine cells; then, level by level, every cell that
    `_needs_refinement` (threshold margin * its diagonal) is split into 8 children, whose corners
    (the 3x3x3 lattice of the parent) are evaluated, and the children are tested in turn. Cells are
    clipped to the grid, so no point outside it is evaluated.

    Returns the sparse store and Int[ndarray, "b 3"]: the blocks that hold fine cells of refined
    cells, the only places the fine grid can have a sign change.
    """
    n = np.array(grid.cells)
    block_counts = tuple(-(-n // _BLOCK))
    store = _SparseValues(grid.shape)
    size = 2**depth
    counts = -(-n // size)
    axes = [np.minimum(np.arange(c + 1) * size, m) for c, m in zip(counts, n)]
    coarse = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    values = sampler(coarse).reshape(tuple(counts + 1))
    store.set_base(axes, values)
    cells = np.stack(np.meshgrid(*[np.arange(c) for c in counts], indexing="ij"), -1).reshape(-1, 3)
    corner_values = np.stack([values[tuple((cells + o).T)] for o in _CORNERS], 1)
    parents = cells[_needs_refinement(corner_values, level, margin * math.sqrt(3) * size * grid.spacing)]
    blocks = []
    while size > 1:
        half = size // 2
        threshold = margin * math.sqrt(3) * half * grid.spacing
        refined = []
        for start in range(0, len(parents), _CELLS_PER_BATCH):
            batch = parents[start : start + _CELLS_PER_BATCH]
            lattice = np.minimum(batch[:, None] * size + _LATTICE * half, n)
            values = store.fill(lattice.reshape(-1, 3), sampler).reshape(-1, 27)
            if half == 1:  # a refined cell of two fine cells lies in one block (_BLOCK is even)
                blocks.append(np.ravel_multi_index(tuple((batch * size // _BLOCK).T), block_counts))
                continue
            children = (batch[:, None] * 2 + _CORNERS).reshape(-1, 3)
            corners = values[:, _CHILD_CORNERS].reshape(-1, 8)
            keep = (children * half < n).all(1) & _needs_refinement(corners, level, threshold)
            refined.append(children[keep])
        parents = np.concatenate(refined) if refined else np.empty((0, 3), np.int64)
        size = half
    found = np.unique(np.concatenate(blocks)) if blocks else np.empty(0, np.int64)
    return store, np.stack(np.unravel_index(found, block_counts), -1).reshape(-1, 3)


# --------------------------------------------------------------------------- blocked marching cubes


@functools.lru_cache(maxsize=1)
def _mask_offset() -> int:
    """Which mask entry enables a cell in skimage's marching cubes: 1 = its upper corner, 0 = its origin.

    skimage (0.19 to at least 0.26) tests mask[x+1, y+1, z+1] for the cell at (x, y, z); this probe
    keeps the code right if that ever changes.
    """
    from skimage.measure import marching_cubes

    volume = np.ones((3, 3, 3), np.float32)
    volume[0, 0, 0] = -1.0  # surface in cell (0, 0, 0) only
    for offset in (1, 0):
        mask = np.zeros(volume.shape, bool)
        mask[offset, offset, offset] = True
        try:
            marching_cubes(volume, 0.0, mask=mask)
            return offset
        except (RuntimeError, ValueError):
            continue
    raise RuntimeError("cannot determine how skimage.measure.marching_cubes reads its mask")


def _cell_reduce(values: np.ndarray, reduce) -> np.ndarray:
    """Combine the 8 corners of every cell: Shaped[ndarray, "X+1 Y+1 Z+1"] -> [..., "X Y Z"]."""
    out = values[:-1, :-1, :-1].copy()
    for dx, dy, dz in _CORNERS[1:]:
        reduce(out, values[dx : dx + out.shape[0], dy : dy + out.shape[1], dz : dz + out.shape[2]], out=out)
    return out


def _surface_cells(values: np.ndarray, level: float) -> np.ndarray:
    """Float[ndarray, "X+1 Y+1 Z+1"] (NaN = unknown) -> Bool[ndarray, "X Y Z"]: cells with all
    corners known and a sign change, the only cells that produce triangles."""
    known = ~np.isnan(values)
    outside = values.astype(np.float64) > level
    return (_cell_reduce(known, np.logical_and) & _cell_reduce(outside, np.logical_or)
            & ~_cell_reduce(outside, np.logical_and))


@dataclass
class _UnitMesh:
    """Marching cubes of one unit (a set of blocks), in grid coordinates."""

    points: np.ndarray
    """Float[ndarray, "v 3"]: vertices in grid index units (float32 output of skimage + box origin)."""
    faces: np.ndarray
    """Int[ndarray, "f 3"]: outward oriented, indices into `points`."""
    keys: np.ndarray
    """Int[ndarray, "v"]: grid edge (3 * linear index of its lower point + axis) of vertices that lie
    on a sign-changing edge, else -1."""
    pinned: np.ndarray
    """Int[ndarray, "p 3"]: vertices that rounded onto a grid point (their edge is ambiguous)."""


def _mesh_unit(values: np.ndarray, lo: np.ndarray, members: np.ndarray, grid_shape, level: float
               ) -> _UnitMesh:
    """Marching cubes on the member blocks of one unit.

    values: Float[ndarray, "X+1 Y+1 Z+1"] grid values of the unit's bounding box starting at grid
    point `lo` (NaN = unknown); members: Int[ndarray, "m 3"] block indices. Only surface cells of
    member blocks are processed (skimage's mask), so units never produce the same triangle twice.
    """
    from skimage.measure import marching_cubes

    cells = _surface_cells(values, level)
    owned = np.zeros_like(cells)
    for block in members:
        start = block * _BLOCK - lo
        owned[start[0] : start[0] + _BLOCK, start[1] : start[1] + _BLOCK, start[2] : start[2] + _BLOCK] = True
    cells &= owned
    if not cells.any():
        no_index = np.empty((0, 3), np.int64)
        return _UnitMesh(np.empty((0, 3)), no_index, np.empty(0, np.int64), no_index)
    mask = np.zeros(values.shape, bool)
    offset = _mask_offset()
    x, y, z = cells.shape
    mask[offset : offset + x, offset : offset + y, offset : offset + z] = cells
    volume = np.where(np.isnan(values), np.float32(level), values).astype(np.float32)
    verts, faces, _, _ = marching_cubes(volume, level, mask=mask)  # "descent": outward for f < 0 inside

    points = verts.astype(np.float64) + lo
    integral = points == np.round(points)
    keys = np.full(len(points), -1, dtype=np.int64)
    on_edge = np.flatnonzero(integral.sum(1) == 2)
    axis = np.argmin(integral[on_edge], axis=1)
    lower = np.floor(points[on_edge]).astype(np.int64)
    upper = lower.copy()
    upper[np.arange(len(axis)), axis] += 1
    local_lo, local_up = tuple((lower - lo).T), tuple((upper - lo).T)
    changes = (values[local_lo].astype(np.float64) > level) != (values[local_up].astype(np.float64) > level)
    keys[on_edge[changes]] = 3 * np.ravel_multi_index(tuple(lower[changes].T), grid_shape) + axis[changes]
    pinned = np.round(points[integral.all(1)]).astype(np.int64)
    return _UnitMesh(points, faces.astype(np.int64), keys, pinned)


def _blocks_touching(point: np.ndarray, block_counts: np.ndarray) -> list[tuple[int, int, int]]:
    """The (up to 8) blocks whose closed box holds grid point Int[ndarray, "3"]."""
    options = []
    for p, count in zip(point, block_counts):
        axis = {p // _BLOCK, (p - 1) // _BLOCK} if p % _BLOCK == 0 else {p // _BLOCK}
        options.append([b for b in axis if 0 <= b < count])
    return list(itertools.product(*options))


def _weld_units(box: Callable[[np.ndarray, np.ndarray], np.ndarray], blocks: np.ndarray, grid: Grid,
                level: float) -> tuple[np.ndarray, np.ndarray, bool]:
    """Marching cubes block by block, welded into one mesh.

    box(lo, hi) returns the grid values of points lo..hi (NaN = unknown); blocks: Int[ndarray, "b 3"]
    blocks that may hold surface cells. Every block starts as its own unit. A vertex shared by two
    units lies on a grid edge in their common face; skimage writes it as float32(x + t), exact in two
    coordinates, so the edge is read off the position and the units' copies are merged by edge.
    Where that fails (t so close to 0 or 1 that the vertex rounded onto a grid point, or two vertices
    of a unit claiming one shared edge) the units involved are merged into one and redone, so the
    result is always the single dense marching-cubes mesh, up to float32 rounding of positions.

    Returns Float[ndarray, "v 3"] vertices in grid units, Int[ndarray, "f 3"] faces, and whether the
    surface reaches the outer boundary of the grid (an open mesh).
    """
    cells = np.array(grid.cells)
    block_counts = -(-cells // _BLOCK)
    owner = np.full(block_counts, -1, dtype=np.int64)  # block -> unit
    units: list[np.ndarray] = []
    meshes: list[_UnitMesh | None] = []

    def add_unit(members: np.ndarray) -> None:
        owner[tuple(members.T)] = len(units)
        units.append(members)
        meshes.append(None)

    for block in blocks:
        add_unit(block[None])
    while True:
        for u, members in enumerate(units):
            if meshes[u] is None and len(members):
                lo = members.min(0) * _BLOCK
                hi = np.minimum((members.max(0) + 1) * _BLOCK, cells)
                meshes[u] = _mesh_unit(box(lo, hi), lo, members, grid.shape, level)
                if not len(meshes[u].faces):  # no surface cell: not a unit (and never merged)
                    owner[tuple(members.T)] = -1
                    units[u] = np.empty((0, 3), np.int64)
        merge = _ambiguous_units(meshes, owner, block_counts)
        if not merge:
            break
        for members in _connected(merge, [u for u in range(len(units)) if len(units[u])]):
            if len(members) > 1:
                joined = np.concatenate([units[u] for u in members])
                for u in members:
                    units[u], meshes[u] = np.empty((0, 3), np.int64), None
                add_unit(joined)
        log.debug("merged blocks into %d units after ambiguous welds", sum(len(u) > 0 for u in units))

    # units in a fixed order (by their first block), so equal inputs give identical meshes
    order = sorted((u for u in range(len(units)) if len(units[u]) and meshes[u] is not None
                    and len(meshes[u].faces)),
                   key=lambda u: tuple(units[u][np.lexsort(units[u].T[::-1])][0]))
    if not order:
        return np.empty((0, 3)), np.empty((0, 3), np.int64), False
    points = np.concatenate([meshes[u].points for u in order])
    keys = np.concatenate([meshes[u].keys for u in order])
    unit_of = np.concatenate([np.full(len(meshes[u].points), u) for u in order])
    sizes = np.cumsum([0] + [len(meshes[u].points) for u in order])
    faces = np.concatenate([meshes[u].faces + s for u, s in zip(order, sizes)])

    # weld: vertices of different units on one shared edge become the first of them
    representative = np.arange(len(points))
    keyed = np.flatnonzero(keys >= 0)
    if len(keyed):
        _, first, inverse = np.unique(keys[keyed], return_index=True, return_inverse=True)
        first_unit = unit_of[keyed[first]]
        shared = np.zeros(len(first), bool)
        np.logical_or.at(shared, inverse, unit_of[keyed] != first_unit[inverse])
        welded = shared[inverse]
        representative[keyed[welded]] = keyed[first][inverse[welded]]
    points, faces = _collapse(points, faces, representative)
    points, faces = _merge_grid_point_vertices(points, faces, grid.shape)
    open_mesh = bool(((points == 0) | (points == cells)).any())
    return points, faces, open_mesh


def _connected(groups: list[set[int]], items: list[int]) -> list[list[int]]:
    """Union-find: `items` partitioned so that each of `groups` lies within one part."""
    parent = {u: u for u in items}

    def find(u: int) -> int:
        while parent[u] != u:
            parent[u] = parent[parent[u]]
            u = parent[u]
        return u

    for group in groups:
        roots = sorted({find(u) for u in group})
        for root in roots[1:]:
            parent[root] = roots[0]
    parts: dict[int, list[int]] = {}
    for u in items:
        parts.setdefault(find(u), []).append(u)
    return list(parts.values())


def _collapse(points: np.ndarray, faces: np.ndarray, representative: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray]:
    """Replace every vertex by Int[ndarray, "v"] `representative` (itself or an earlier vertex),
    drop the unused ones and the faces that lost a corner."""
    keep = representative == np.arange(len(points))
    new_index = np.cumsum(keep) - 1
    faces = new_index[representative[faces]]
    whole = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 2] != faces[:, 0])
    return points[keep], faces[whole]


def _merge_grid_point_vertices(points: np.ndarray, faces: np.ndarray, shape) -> tuple[np.ndarray, np.ndarray]:
    """One vertex per grid point: where the field is (within float32) at the level on a grid point,
    marching cubes puts one vertex there per crossing edge, joined by zero-area slivers. Merge them
    and drop the slivers, so the mesh is closed also when coincident vertices count as one."""
    on_point = np.flatnonzero((points == np.round(points)).all(1))
    representative = np.arange(len(points))
    if len(on_point):
        linear = np.ravel_multi_index(tuple(np.round(points[on_point]).astype(np.int64).T), shape)
        _, first, inverse = np.unique(linear, return_index=True, return_inverse=True)
        representative[on_point] = on_point[first][inverse]
    return _collapse(points, faces, representative)


def _ambiguous_units(meshes: list[_UnitMesh | None], owner: np.ndarray, block_counts: np.ndarray
                     ) -> list[set[int]]:
    """Groups of units whose shared vertices cannot be matched by edge and must be meshed together."""
    merge: list[set[int]] = []
    for mesh in meshes:  # vertices rounded onto a grid point that several units touch
        if mesh is None or not len(mesh.pinned):
            continue
        on_face = mesh.pinned[(mesh.pinned % _BLOCK == 0).any(1)]
        for point in np.unique(on_face, axis=0):
            near = {int(owner[b]) for b in _blocks_touching(point, block_counts)} - {-1}
            if len(near) > 1:
                merge.append(near)
    live = [(u, m) for u, m in enumerate(meshes) if m is not None and len(m.keys)]
    if live:  # one shared edge claimed by two vertices of one unit
        count = len(meshes)
        keys = np.concatenate([m.keys for _, m in live])
        unit = np.concatenate([np.full(len(m.keys), u) for u, m in live])
        pick = keys >= 0
        pairs, repeats = np.unique(keys[pick] * count + unit[pick], return_counts=True)  # (key, unit)
        pair_keys = pairs // count
        keys_of_units, units_per_key = np.unique(pair_keys, return_counts=True)
        clash = np.intersect1d(pair_keys[repeats > 1], keys_of_units[units_per_key > 1])
        for key in clash:
            merge.append(set((pairs[pair_keys == key] % count).tolist()))
    return merge


def _dense_surface_blocks(values: np.ndarray, level: float) -> np.ndarray:
    """Float[ndarray, "X+1 Y+1 Z+1"] -> Int[ndarray, "b 3"]: blocks with at least one surface cell."""
    cells = np.array(values.shape) - 1
    counts = -(-cells // _BLOCK)
    found = []
    for block in itertools.product(*[range(c) for c in counts]):
        lo = np.array(block) * _BLOCK
        hi = np.minimum(lo + _BLOCK, cells)
        piece = values[lo[0] : hi[0] + 1, lo[1] : hi[1] + 1, lo[2] : hi[2] + 1].astype(np.float64) > level
        if piece.any() and not piece.all() and _surface_cells(values[lo[0] : hi[0] + 1, lo[1] : hi[1] + 1,
                                                                      lo[2] : hi[2] + 1], level).any():
            found.append(block)
    return np.array(found, dtype=np.int64).reshape(-1, 3)


# ------------------------------------------------------------------------------------ public API


def extract_mesh(
    field: Field,
    resolution: int = 256,
    bounds=None,
    level: float = 0.0,
    chunk_size: int = 262_144,
    coarse_to_fine: bool = True,
    device: torch.device | str | None = None,
    *,
    margin: float = 2.0,
    coarse_resolution: int = 64,
) -> Mesh:
    """Marching cubes of the `level` set of `field` inside `bounds`, in the world frame.

    field: callable x[..., 3] float32 (world) -> f[...], negative inside (an nn.Module or a function).
    resolution: cells along the longest side of the box; voxels are cubes (see `make_grid`).
    bounds: (2, 3) min/max world corners; None uses `field.bounds`.
    chunk_size: points per field call (memory vs. speed; does not change the result).
    coarse_to_fine: evaluate the full resolution only near the surface (below); False samples the
        whole grid. Both give the same mesh for fields whose Lipschitz constant is at most 2 * margin.
    device: where to evaluate a plain function (an nn.Module is evaluated where its parameters are).
    margin: coarse-to-fine refines a cell of diagonal d when its corner values straddle `level` or
        come within margin * d of it; safe (identical to dense) for fields with |grad f| <= 2 * margin.
        The default 2.0 allows gradients four times those of an exact SDF.
    coarse_resolution: cells along the longest side of the first coarse-to-fine level (rounded so
        that the fine grid is a power-of-two refinement of it).

    Returns a Mesh (float32 vertices, outward counter-clockwise faces) that is watertight unless the
    surface leaves the box, in which case a warning says so. Raises ExtractionError when the field
    has no sign change in the box or returns NaN.
    """
    if not callable(field):
        raise InputError(f"field must be callable x[..., 3] -> f[...], got {type(field).__name__}")
    if not (isinstance(margin, (int, float)) and margin > 0 and math.isfinite(margin)):
        raise ConfigError(
            f"margin must be a positive number (multiples of the cell diagonal), got {margin!r}"
        )
    if not (isinstance(coarse_resolution, (int, np.integer)) and coarse_resolution >= 1):
        raise ConfigError(f"coarse_resolution must be a positive integer, got {coarse_resolution!r}")
    level = float(level)
    if not math.isfinite(level):
        raise ConfigError(f"level must be a finite number, got {level}")
    box = _resolve_bounds(field, bounds)
    grid = make_grid(box, resolution)
    sampler = _Sampler(field, grid, chunk_size, _field_device(field, device))
    depth = max(0, math.floor(math.log2(resolution / coarse_resolution))) if coarse_to_fine else 0

    if depth > 0:
        store, blocks = _coarse_to_fine(sampler, grid, level, float(margin), depth)
        box_values = store.box
    else:
        dense = sampler.dense()
        blocks = _dense_surface_blocks(dense, level)

        def box_values(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
            return dense[lo[0] : hi[0] + 1, lo[1] : hi[1] + 1, lo[2] : hi[2] + 1]

    log.debug("extract_mesh: %d field evaluations for a %s grid", sampler.evaluations, grid.shape)
    points, faces, open_mesh = _weld_units(box_values, blocks, grid, level)
    if len(faces) == 0:
        raise ExtractionError(
            f"the field has no {level:g}-level set in the box {box.tolist()}: over the {sampler.evaluations} "
            f"points sampled its values lie in [{sampler.low:.4g}, {sampler.high:.4g}]; pass bounds that "
            f"contain the surface, or a level between those values"
        )
    if open_mesh:
        warnings.warn(
            f"the surface touches the boundary of the extraction box {box.tolist()}, so the mesh is cut "
            f"open there (it will not be watertight); pass larger bounds to get a closed mesh",
            stacklevel=2,
        )
    vertices = grid.origin + points * grid.spacing
    return Mesh(torch.from_numpy(vertices.astype(np.float32)), torch.from_numpy(faces))


# ----------------------------------------------------------------------------------- slices

_AXES = {"x": 0, "y": 1, "z": 2, 0: 0, 1: 1, 2: 2}


def field_slice(
    field: Field,
    bounds=None,
    axis: str | int = "z",
    position: float = 0.5,
    resolution: int = 256,
    device: torch.device | str | None = None,
) -> Tensor:
    """Field values on an axis-aligned plane of the box: Float[Tensor, "H W"] on the CPU.

    The plane is normal to `axis` at `position` (a fraction, 0 = min, 1 = max side of the box).
    Its in-plane axes are (u, v) = the other two axes in x, y, z order: columns run along u,
    rows along v with row 0 at the largest v (images show v upwards). Samples sit at pixel centres
    with square pixels; `resolution` pixels span the longer in-plane side.
    """
    if axis not in _AXES:
        raise ConfigError(f"axis must be one of 'x', 'y', 'z' (or 0, 1, 2), got {axis!r}")
    if not (0.0 <= float(position) <= 1.0):
        raise ConfigError(f"position is a fraction of the box along the axis, in [0, 1]; got {position}")
    if not (isinstance(resolution, (int, np.integer)) and resolution >= 1):
        raise ConfigError(f"resolution must be a positive integer, got {resolution!r}")
    box = _resolve_bounds(field, bounds)
    normal = _AXES[axis]
    u, v = [a for a in range(3) if a != normal]
    extent = box[1] - box[0]
    pixel = max(extent[u], extent[v]) / resolution
    width, height = (max(1, round(extent[a] / pixel)) for a in (u, v))
    us = box[0, u] + (np.arange(width) + 0.5) * extent[u] / width
    vs = box[0, v] + (np.arange(height)[::-1] + 0.5) * extent[v] / height
    points = np.empty((height, width, 3), dtype=np.float64)
    points[..., normal] = box[0, normal] + float(position) * extent[normal]
    points[..., u] = us[None, :]
    points[..., v] = vs[:, None]
    x = torch.from_numpy(points.reshape(-1, 3).astype(np.float32)).to(_field_device(field, device))
    with torch.no_grad():
        values = torch.cat([field(chunk).reshape(-1).to("cpu", torch.float32) for chunk in x.split(262_144)])
    return values.reshape(height, width)


_INSIDE = np.array([0.230, 0.299, 0.754])  # blue (negative)
_OUTSIDE = np.array([0.706, 0.016, 0.150])  # red (positive)


def slice_image(values, max_abs: float | None = None, bands: int = 10) -> np.ndarray:
    """Float[Tensor | ndarray, "H W"] field values -> UInt8[ndarray, "H W 3"] RGB picture.

    Diverging colours (blue negative, white at 0, red positive, saturating at `max_abs`, default
    the largest |value|), darker iso-contour bands every max_abs / bands, and the zero level in
    black (pixels on the negative side of a sign change with a 4-neighbour). NaN pixels are grey.
    """
    if isinstance(values, Tensor):
        values = values.detach().cpu().double().numpy()
    f = np.asarray(values, np.float64)
    if f.ndim != 2:
        raise InputError(f"slice_image expects an (H, W) array of field values, got shape {f.shape}")
    finite = np.isfinite(f)
    if max_abs is None:
        max_abs = float(np.abs(f[finite]).max()) if finite.any() else 1.0
    max_abs = max_abs if max_abs > 0 else 1.0
    g = np.where(finite, f, 0.0)
    t = np.clip(g / max_abs, -1.0, 1.0)[..., None]
    colour = np.where(t < 0, 1 + (-t) * (_INSIDE - 1), 1 + t * (_OUTSIDE - 1))
    phase = np.abs(g) / max_abs * bands
    colour *= np.where((phase % 1.0) < 0.5, 1.0, 0.85)[..., None]  # contour bands
    inside = g <= 0
    edge = np.zeros_like(inside)
    edge[:-1] |= inside[:-1] & ~inside[1:]
    edge[1:] |= inside[1:] & ~inside[:-1]
    edge[:, :-1] |= inside[:, :-1] & ~inside[:, 1:]
    edge[:, 1:] |= inside[:, 1:] & ~inside[:, :-1]
    colour[edge] = 0.0
    colour[~finite] = 0.5
    return np.round(np.clip(colour, 0, 1) * 255).astype(np.uint8)


__all__ = ["Grid", "extract_mesh", "field_slice", "make_grid", "slice_image"]
