"""Field -> Mesh: marching cubes on a grid of cubic voxels, evaluated in chunks, densely or
coarse-to-fine; slices of fields for TensorBoard.

A field is any callable mapping world points x[..., 3] (float32 tensor; float64 where float32 cannot
hold the grid's points, far from the origin for its cells) to values f[...], negative inside. Meshes
come back in the world frame with faces oriented outward (towards positive f).
Coarse-to-fine evaluates a coarse grid, then refines, level by level, only the cells that may hold
the surface; every other grid point gets the trilinear interpolation of its coarse cell, whose
sign is right wherever the field is Lipschitz (below), so one marching-cubes call over the whole
grid gives exactly the dense result. Never imports neuralsurf.models or training.
"""

from __future__ import annotations

import itertools
import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor, nn

from neuralsurf.errors import ConfigError, ExtractionError, InputError
from neuralsurf.geometry import float32_holds, take_rows
from neuralsurf.io.npz import write_npz
from neuralsurf.marching import cube_triangles, marching_cubes_torch, merge_edge_vertices
from neuralsurf.progress import progress_bar
from neuralsurf.structures import Mesh

Field = Callable[[Tensor], Tensor]


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

    @property
    def dtype(self) -> type:
        """The type of its world coordinates: np.float32, or np.float64 where float32 would round them by more than
        `geometry.ROUNDING` of a cell (a grid far from the origin for its cells: georeferenced data)."""
        far = float(np.abs(self.origin).max()) + max(self.cells) * self.spacing
        return np.float32 if float32_holds(far, self.spacing) else np.float64

    def world(self, index: np.ndarray) -> np.ndarray:
        """Float[ndarray, "n 3"] grid indices (whole for grid points, fractional for vertices) -> Float[ndarray,
        "n 3"] world points of `dtype`.

        The one place grid points become coordinates, so a point gets bit-identical input (and, for
        a deterministic field, value) whichever code path or chunk evaluates it.
        """
        return (self.origin + index.astype(np.float64) * self.spacing).astype(self.dtype)


def make_grid(bounds, resolution: int) -> Grid:
    """The marching-cubes grid for a (2, 3) box: `resolution` cells along its longest side.

    Every axis uses the same spacing (cubic voxels); the shorter axes get enough cells to cover
    the box and are centred on it, so the grid covers the box and overhangs it by less than one cell.
    """
    box = as_bounds(bounds)
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


def as_bounds(bounds) -> np.ndarray:
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
    return as_bounds(bounds)


def field_device(field: Field, device: torch.device | str | None) -> torch.device:
    """Where to evaluate: a module's parameters (or buffers) decide, else `device`, else CPU."""
    if isinstance(field, nn.Module):
        for tensor in itertools.chain(field.parameters(), field.buffers()):
            return tensor.device
    return torch.device(device) if device is not None else torch.device("cpu")


def evaluate_grid_points(field: Field, grid: Grid, index: np.ndarray, chunk_size: int,
                         device: torch.device, progress: bool = False, desc: str = "field") -> np.ndarray:
    """Int[ndarray, "n 3"] grid indices -> Float[ndarray, "n"] float32 field values (no grad), in
    chunks of `chunk_size` points (a progress bar over them when `progress`).

    Raises ExtractionError on NaN, naming a point where it happened.
    """

    values = np.empty(len(index), dtype=np.float32)
    starts = range(0, len(index), chunk_size)
    with torch.no_grad():
        for start in progress_bar(starts, desc=desc, unit="chunk", enabled=progress):
            points = torch.from_numpy(grid.world(index[start : start + chunk_size])).to(device)
            result = field(points)
            if result.shape != points.shape[:-1]:
                raise InputError(
                    f"the field must return one value per point: points {tuple(points.shape)} gave "
                    f"values {tuple(result.shape)}; map x[..., 3] to f[...]"
                )
            values[start : start + chunk_size] = result.to("cpu", torch.float32).numpy()
    if np.isnan(values).any():
        bad = grid.world(index[np.isnan(values)][:1])[0].tolist()
        raise ExtractionError(f"the field returned NaN, e.g. at {bad}; check the model (diverged training?)")
    return values


def _all_points(shape) -> np.ndarray:
    """Int[ndarray, "X*Y*Z 3"]: every index of a grid of `shape` points, in C order."""
    return np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), -1).reshape(-1, 3)


def _cell_extremes(values: Tensor) -> tuple[Tensor, Tensor]:
    """Float[Tensor, "X Y Z"] point values -> min and max over each cell's 8 corners, [X-1, Y-1, Z-1]."""
    corners = (values[i : values.shape[0] - 1 + i, j : values.shape[1] - 1 + j, k : values.shape[2] - 1 + k]
               for i, j, k in itertools.product((0, 1), repeat=3))
    low = next(corners).clone()
    high = low.clone()
    for corner in corners:  # running extremes: two grids in memory, not eight
        torch.minimum(low, corner, out=low)
        torch.maximum(high, corner, out=high)
    return low, high


def cells_near_level(values: Tensor, level: float, threshold: float) -> Tensor:
    """Bool[Tensor, "X-1 Y-1 Z-1"]: cells whose corners straddle `level` or come within `threshold`."""
    low, high = _cell_extremes(values - level)
    return (low <= threshold) & (high >= -threshold)


def _points_of_cells(cells: Tensor) -> Tensor:
    """Bool[Tensor, "X-1 Y-1 Z-1"] cells -> Bool[Tensor, "X Y Z"]: the corners of those cells (one bool
    grid: a max-pool over a float copy took 8x its memory)."""
    points = torch.zeros(tuple(n + 1 for n in cells.shape), dtype=torch.bool, device=cells.device)
    x, y, z = cells.shape
    for i, j, k in itertools.product((0, 1), repeat=3):
        points[i : i + x, j : j + y, k : k + z] |= cells
    return points


def _level_shape(grid: Grid, stride: int) -> tuple[int, ...]:
    return tuple(math.ceil(c / stride) + 1 for c in grid.cells)


def _coarse_to_fine_values(field: Field, grid: Grid, level: float, margin: float, depth: int,
                           chunk_size: int, device: torch.device, progress: bool = False) -> tuple[np.ndarray, int]:
    """Float[ndarray, "X Y Z"] values on the whole grid, evaluating the field only near the surface.

    At stride s (grid points s cells apart) a cell of diagonal d = s * spacing * sqrt(3) is refined
    when its corners straddle `level` or one lies within margin * d of it. Every point of a cube is
    within d / 2 of a corner, so a field with |grad f| <= 2 * margin cannot reach `level` inside an
    unrefined cell: interpolated values there have the right sign. Returns the values and the
    number of field evaluations. The bookkeeping (interpolation, refinement masks) runs on `device`.
    """
    stride = 2**depth
    index = _all_points(_level_shape(grid, stride)) * stride  # the last layer may overhang the grid
    values = torch.from_numpy(evaluate_grid_points(field, grid, index, chunk_size, device, progress,
                                                   f"extract 1/{depth + 1}"))
    values = values.reshape(_level_shape(grid, stride)).to(device)
    evaluations = len(index)
    active = cells_near_level(values, level, margin * stride * grid.spacing * math.sqrt(3))
    while stride > 1:
        stride //= 2
        shape = _level_shape(grid, stride)
        doubled = tuple(2 * n - 1 for n in values.shape)  # points at half steps of the previous level
        values = torch.nn.functional.interpolate(values[None, None], size=doubled, mode="trilinear",
                                                 align_corners=True)[0, 0][: shape[0], : shape[1], : shape[2]]
        children = active.repeat_interleave(2, 0).repeat_interleave(2, 1).repeat_interleave(2, 2)
        children = children[: shape[0] - 1, : shape[1] - 1, : shape[2] - 1]
        todo = _points_of_cells(children)
        todo_index = todo.nonzero().cpu().numpy()
        level_name = f"extract {depth + 1 - int(math.log2(stride))}/{depth + 1}"
        values[todo] = torch.from_numpy(
            evaluate_grid_points(field, grid, todo_index * stride, chunk_size, device, progress, level_name)
        ).to(device)
        evaluations += len(todo_index)
        active = children & cells_near_level(values, level, margin * stride * grid.spacing * math.sqrt(3))
    return values[: grid.shape[0], : grid.shape[1], : grid.shape[2]].contiguous().cpu().numpy(), evaluations


_CORNER_STEPS = torch.tensor([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
"""Int64[Tensor, "8 3"]: a cell's corners (and a cell's children) as offsets, i-major (marching's order)."""


def _linear(index: Tensor, shape) -> Tensor:
    """Int64[Tensor, "... 3"] grid indices -> Int64[Tensor, "..."] i-major linear indices in a grid of `shape`."""
    return (index[..., 0] * shape[1] + index[..., 1]) * shape[2] + index[..., 2]


_LATTICE_STEPS = torch.tensor([[i, j, k] for i in range(3) for j in range(3) for k in range(3)])
"""Int64[Tensor, "27 3"]: the points of a cell's 2 x 2 x 2 children, as offsets from its first child's first corner."""


def _children_values(field: Field, grid: Grid, cells: Tensor, stride: int, chunk_size: int,
                     device: torch.device) -> tuple[Tensor, Tensor, int]:
    """The children of Int64[Tensor, "m 3"] `cells` of the level 2 * `stride` at the level `stride` (grid points
    `stride` apart) that lie inside the grid: (their indices Int64[Tensor, "c 3"], the field at their corners
    Float[Tensor, "c 2 2 2"], the number of field evaluations: each point of the cells' 3 x 3 x 3 lattices once)."""
    shape = _level_shape(grid, stride)
    inside = 2 * cells[:, :, None] + torch.arange(3) < torch.tensor(shape)[:, None]  # [m, axis, step]
    inside = (inside[:, 0, :, None, None] & inside[:, 1, None, :, None] & inside[:, 2, None, None, :]).reshape(-1, 27)
    small = math.prod(shape) < 2**31  # int32 sorts about twice as fast
    first = _linear(2 * cells, shape).to(torch.int32 if small else torch.int64)
    linear = torch.where(inside, first[:, None] + _linear(_LATTICE_STEPS, shape).to(first), -1)  # [m, 27]
    points, inverse = torch.unique(linear, return_inverse=True)
    outside = bool(points[0] < 0)  # lattice points beyond the grid: never a corner of a child inside it
    points = points[int(outside):].long()
    index = torch.stack([points // (shape[1] * shape[2]), points // shape[2] % shape[1], points % shape[2]], -1)
    values = torch.from_numpy(evaluate_grid_points(field, grid, index.numpy() * stride, chunk_size, device))
    if outside:
        values = torch.cat([values.new_full((1,), math.nan), values])
    block = take_rows(values, inverse).reshape(-1, 3, 3, 3)
    corners = block.unfold(1, 2, 1).unfold(2, 2, 1).unfold(3, 2, 1).reshape(-1, 2, 2, 2)  # child-major, i-major
    children = (2 * cells[:, None] + _CORNER_STEPS).reshape(-1, 3)
    kept = (children < torch.tensor(shape) - 1).all(-1)
    return children[kept], corners[kept], len(points)


def _sparse_surface(field: Field, grid: Grid, level: float, margin: float, depth: int, chunk_size: int,
                    device: torch.device, block: int = 1 << 17) -> tuple[Tensor, Tensor, bool, int]:
    """Coarse-to-fine marching cubes with memory and time in proportion to the surface: the refinement of
    `_coarse_to_fine_values` (the same cells, the same field evaluations), kept as lists of cells rather than
    dense grids, `block` cells at a time, and the finest cells that the level crosses marched as 2 x 2 x 2 cubes
    (`marching.cube_triangles`, vertices joined by grid edge). Returns (vertices Float64[Tensor, "v 3"] in grid
    units, faces Int64[Tensor, "f 3"] oriented towards values above `level`, whether a value at or below the
    level lies on the grid's boundary, field evaluations)."""
    stride = 2**depth
    shape = _level_shape(grid, stride)
    coarse = evaluate_grid_points(field, grid, _all_points(shape) * stride, chunk_size, device)
    coarse = torch.from_numpy(coarse).reshape(shape)
    cells = cells_near_level(coarse, level, margin * stride * grid.spacing * math.sqrt(3)).nonzero()
    evaluations, touches = coarse.numel(), bool((coarse[[0, -1]] <= level).any() or (coarse[:, [0, -1]] <= level).any()
                                                or (coarse[:, :, [0, -1]] <= level).any())
    keys, positions = [], []
    while stride > 1 and len(cells):
        stride //= 2
        limit = torch.tensor(_level_shape(grid, stride)) - 1  # cells per axis at this level
        threshold = margin * stride * grid.spacing * math.sqrt(3)
        refined = []
        for part in cells.split(block):
            children, values, count = _children_values(field, grid, part, stride, chunk_size, device)
            evaluations += count
            values = values.reshape(-1, 8)
            low, high = values.min(1).values - level, values.max(1).values - level
            if stride > 1:
                refined.append(children[(low <= threshold) & (high >= -threshold)])
                continue
            on_side = (children == 0) | (children == limit - 1)  # the grid's outer cells
            touches |= bool((on_side.any(-1)[:, None] & (values <= level)).any())
            crossed = (low < 0) & (high >= 0)
            values = _off_level_corners(values[crossed].double(), level)
            k, p = cube_triangles(values.reshape(-1, 2, 2, 2), None, children[crossed], grid.shape, level)
            keys.append(k)
            positions.append(p)
        if stride > 1:
            cells = torch.cat(refined)
    if not keys or not sum(len(k) for k in keys):
        return torch.zeros(0, 3, dtype=torch.float64), torch.zeros(0, 3, dtype=torch.long), touches, evaluations
    vertices, faces = merge_edge_vertices(torch.cat(keys), torch.cat(positions))
    return vertices, faces.long(), touches, evaluations


def _off_level_corners(values: Tensor, level: float, min_fraction: float = 1e-4) -> Tensor:
    """Float[Tensor, "m 8"] corner values with none nearer to `level` than `min_fraction` of the cells' value range
    (moved away from it, its side kept; exactly at the level counts as above): `off_level` for cells marched
    apart, so that two vertices of a corner's edges never land on one position (a pinched mesh)."""
    spread = (values.max(1, keepdim=True).values - values.min(1, keepdim=True).values).clamp_min(1e-30)
    gap = min_fraction * spread
    close = (values - level).abs() < gap
    return torch.where(close, level + torch.where(values < level, -gap, gap), values)


def off_level(values: Tensor, level: float, min_fraction: float = 1e-4) -> Tensor:
    """Float[Tensor, "X Y Z"] values with no grid point nearer to `level` than `min_fraction` of its
    difference to any neighbour across the level (that point moved away from the level, its sign
    kept; points exactly at the level are left to marching cubes). Without this a field within ~1e-6
    of the level at a grid point puts the vertices of that point's edges on the same float32
    position, and merging them pinches the mesh (edges of four faces: not watertight)."""
    points = ((values - level).abs_() < min_fraction * float(values.max() - values.min())).nonzero()
    here = values[tuple(points.T)].double() - level
    points, here = points[here != 0], here[here != 0]
    needed = torch.zeros_like(here)
    for axis in range(3):
        for step in (-1, 1):
            neighbour = points.clone()
            neighbour[:, axis] += step
            inside = (neighbour[:, axis] >= 0) & (neighbour[:, axis] < values.shape[axis])
            other = torch.zeros_like(here)
            other[inside] = values[tuple(neighbour[inside].T)].double() - level
            across = inside & (other.sign() == -here.sign())
            needed = torch.where(across, torch.maximum(needed, min_fraction * (other - here).abs()), needed)
    move = here.abs() < needed
    if not move.any():
        return values
    values = values.clone()
    values[tuple(points[move].T)] = (level + here[move].sign() * needed[move]).to(values.dtype)
    return values


def cells_of_points(valid: np.ndarray) -> np.ndarray:
    """Bool[ndarray, "X Y Z"] valid points -> Bool[ndarray, "X-1 Y-1 Z-1"] cells whose 8 corners are all
    valid (a separable erosion: three pairwise ANDs)."""
    cells = valid[:-1] & valid[1:]
    cells = cells[:, :-1] & cells[:, 1:]
    return cells[:, :, :-1] & cells[:, :, 1:]


def level_set(values: np.ndarray, level: float = 0.0, valid: np.ndarray | None = None,
              device: torch.device | str = "cpu") -> tuple[np.ndarray, np.ndarray]:
    """Marching cubes of the `level` set of Float[ndarray, "X Y Z"] point values, in grid units.

    valid: Bool[ndarray, "X Y Z"] points with a value (e.g. observed TSDF voxels): a cell with an invalid
    corner gets no faces. Returns vertices Float32[ndarray, "v 3"] and faces Int64[ndarray, "f 3"],
    oriented towards values above `level`; both empty when no cell holds a face. On a CUDA `device` (no
    `valid`) the cubes are marched there (`neuralsurf.marching`: the same vertices as skimage's,
    ambiguous cells triangulated alike or otherwise); else by skimage's Lewiner marching cubes on the
    CPU, skipping masked cells.
    """
    from skimage.measure import marching_cubes as skimage_marching_cubes

    empty = np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int64)
    finite = values if valid is None else np.where(valid, values, np.float32(level + 1.0))
    if not float(finite.min()) < level < float(finite.max()):
        return empty
    on_gpu = torch.device(device).type == "cuda" and valid is None
    finite = off_level(torch.from_numpy(finite).to(device if on_gpu else "cpu"), level)
    if on_gpu:
        vertices, faces = (t.cpu().numpy() for t in marching_cubes_torch(finite, level))
        return vertices.astype(np.float32), faces.astype(np.int64)
    mask = None
    if valid is not None:
        keep = cells_of_points(valid)
        if not keep.any():
            return empty
        mask = np.zeros(values.shape, dtype=bool)
        mask[1:, 1:, 1:] = keep  # skimage reads a cell's mask at its last corner
    try:
        vertices, faces, _, _ = skimage_marching_cubes(finite.numpy(), level, mask=mask, allow_degenerate=False)
    except RuntimeError:  # "No surface found": every cell with a sign change is masked
        return empty
    return vertices.astype(np.float32), faces.astype(np.int64)  # outward


def marching_cubes(values: np.ndarray, grid: Grid, level: float = 0.0, valid: np.ndarray | None = None,
                   device: torch.device | str = "cpu") -> Mesh:
    """Float[ndarray, "X Y Z"] values at the grid points -> Mesh of the `level` set (world frame,
    faces oriented towards values above `level`), by `level_set`: cells with a corner where `valid`
    (Bool[ndarray, "X Y Z"]) is False produce no faces (e.g. unobserved TSDF voxels). Raises
    ExtractionError if no face remains."""
    vertices, faces = level_set(values, level, valid, device=device)
    if len(faces) == 0:  # say why: no value on both sides of the level, or none in a valid cell
        finite = values if valid is None else np.where(valid, values, level + 1.0).astype(values.dtype)
        low, high = float(finite.min()), float(finite.max())
        if not low < level < high:
            constant = ("; the field is constant there, as a diverged fit leaves it: lower the learning rate and fit "
                        "again" if high - low <= 1e-6 * max(1.0, abs(low), abs(high)) else "")
            raise ExtractionError(
                f"the field has no {level:g}-level set in the box: its values there lie in [{low:.4g}, {high:.4g}]; "
                f"pass bounds that contain the surface, or a level between those values{constant}"
            )
        raise ExtractionError("marching cubes found no faces in the valid part of the grid")
    return Mesh(torch.from_numpy(grid.world(vertices)), torch.from_numpy(faces))


def extract_mesh(
    field: Field,
    resolution: int = 256,
    bounds=None,
    level: float = 0.0,
    chunk_size: int = 262_144,
    coarse_to_fine: bool = True,
    device: torch.device | str | None = None,
    *,
    margin: float = 1.0,
    coarse_resolution: int = 64,
    progress: bool = True,
    sparse: bool = False,
) -> Mesh:
    """Marching cubes of the `level` set of `field` inside `bounds`, in the world frame.

    field: callable x[..., 3] (world, of `Grid.dtype`) -> f[...], negative inside (an nn.Module or a function).
    resolution: cells along the longest side of the box; voxels are cubes (see `make_grid`).
    bounds: (2, 3) min/max world corners; None uses `field.bounds`.
    chunk_size: points per field call (memory vs. speed; does not change the result).
    coarse_to_fine: evaluate the full resolution only near the surface; False samples the whole
        grid. Both give the same mesh for fields with |grad f| <= 2 * margin.
    device: where to evaluate a plain function (an nn.Module is evaluated where its parameters are).
    margin: coarse-to-fine refines a cell of diagonal d when its corner values come within
        margin * d of `level`; the default 1.0 allows gradients twice those of an exact SDF (a fitted
        SDF's mesh is the same as with 2.0, from a third fewer evaluations).
    coarse_resolution: cells along the longest side of the first coarse-to-fine level (the fine
        grid is a power-of-two refinement of it).
    progress: a progress bar over the field's chunks when the evaluation lasts more than a few
        seconds (neuralsurf.progress); False for none.
    sparse: coarse-to-fine with memory and time in proportion to the surface, not the grid's volume
        (`_sparse_surface`: the same field evaluations, lists of cells instead of dense grids, the crossed
        cells marched apart and joined by grid edge); the mesh has the vertices of the dense one, its
        ambiguous cells may be triangulated differently. For fine grids (1024^3 holds 4 GB of values).

    Returns a Mesh (vertices of the grid's `Grid.dtype`: float32 unless the box lies far from the origin for its
    cells; outward faces), watertight unless the surface leaves the box,
    in which case a warning says so. Raises ExtractionError when the field has no sign change in the
    box or returns NaN.
    """
    if not callable(field):
        raise InputError(f"field must be callable x[..., 3] -> f[...], got {type(field).__name__}")
    if not (isinstance(margin, (int, float)) and margin > 0 and math.isfinite(margin)):
        raise ConfigError(f"margin must be a positive number (multiples of the cell diagonal), got {margin!r}")
    if not (isinstance(coarse_resolution, (int, np.integer)) and coarse_resolution >= 1):
        raise ConfigError(f"coarse_resolution must be a positive integer, got {coarse_resolution!r}")
    if not (isinstance(chunk_size, (int, np.integer)) and chunk_size >= 1):
        raise ConfigError(f"chunk_size must be a positive integer (points per field call), got {chunk_size!r}")
    if not math.isfinite(level):
        raise ConfigError(f"level must be a finite number, got {level}")
    box = _resolve_bounds(field, bounds)
    grid = make_grid(box, resolution)
    device = field_device(field, device)
    depth = max(0, math.floor(math.log2(resolution / coarse_resolution))) if coarse_to_fine else 0
    if sparse and depth:
        vertices, faces, touches, _ = _sparse_surface(field, grid, float(level), float(margin), depth, chunk_size,
                                                      device)
        if not len(faces):
            raise ExtractionError(f"the field has no {level:g}-level set in the box {box.tolist()}: no cell of the "
                                  f"grid has corners on both sides; pass bounds that contain the surface")
        mesh = Mesh(torch.from_numpy(grid.world(vertices.numpy())), faces)
    elif depth:
        values, _ = _coarse_to_fine_values(
            field, grid, float(level), float(margin), depth, chunk_size, device, progress
        )
    else:
        values = evaluate_grid_points(
            field, grid, _all_points(grid.shape), chunk_size, device, progress, "extract"
        ).reshape(grid.shape)
    if not (sparse and depth):
        mesh = marching_cubes(values, grid, float(level), device=device)
        faces_out = [values[0], values[-1], values[:, 0], values[:, -1], values[:, :, 0], values[:, :, -1]]
        touches = any((side <= level).any() for side in faces_out)
    if touches:
        warnings.warn(
            f"the surface touches the boundary of the extraction box {box.tolist()}, so the mesh is cut "
            f"open there (it will not be watertight); pass larger bounds to get a closed mesh",
            stacklevel=2,
        )
    return mesh


@dataclass(frozen=True)
class GridSamples:
    """A field sampled on a regular grid of cubic cells (`sample_grid`)."""

    values: Tensor
    """Float32[Tensor, "X Y Z"]: the field at grid point (i, j, k) = bounds[0] + (i, j, k) * spacing."""
    bounds: Tensor
    """Float64[Tensor, "2 3"]: world positions of the first and last grid points (the grid's box)."""
    spacing: float
    """World distance between neighbouring grid points, the same along every axis."""

    def points(self) -> Tensor:
        """Float64[Tensor, "X Y Z 3"]: the world position of every grid point."""
        axes = [self.bounds[0, a] + torch.arange(n, dtype=torch.float64) * self.spacing
                for a, n in enumerate(self.values.shape)]
        return torch.stack(torch.meshgrid(*axes, indexing="ij"), -1)


def sample_grid(
    field: Field,
    resolution: int,
    bounds=None,
    path=None,
    *,
    chunk_size: int = 262_144,
    device: torch.device | str | None = None,
    progress: bool = True,
) -> GridSamples:
    """Evaluate `field` on a regular grid, e.g. to export a fitted field to other tools.

    The grid is extraction's (`make_grid`): `resolution` cells along the longest side of `bounds`,
    cubic cells, centred on the box and covering it (so its own box, returned, may overhang `bounds`
    by less than a cell). Values are float32, one field call per `chunk_size` points.

    Args:
        field: callable x[..., 3] (world, of `Grid.dtype`) -> f[...] (an nn.Module is evaluated where its
            parameters are, a plain function on `device`).
        resolution: cells along the longest side (>= 2); the grid has resolution + 1 points there.
        bounds: (2, 3) world box; None uses `field.bounds`.
        path: when given, also write a .npz holding `values` (X, Y, Z) float32, `bounds` (2, 3)
            float64 and `spacing` () float64 (plain arrays: np.load(path) needs no pickle), atomically.
    Returns:
        GridSamples(values Float32[Tensor, "X Y Z"], bounds Float64[Tensor, "2 3"], spacing).
    Raises:
        InputError for a non-callable field, bad bounds or a field that does not return one value per
        point; ConfigError for a bad resolution or chunk_size; ExtractionError if the field returns NaN;
        FileFormatError when `path` cannot be written.
    """
    if not callable(field):
        raise InputError(f"field must be callable x[..., 3] -> f[...], got {type(field).__name__}")
    if not (isinstance(chunk_size, (int, np.integer)) and chunk_size >= 1):
        raise ConfigError(f"chunk_size must be a positive integer (points per field call), got {chunk_size!r}")
    grid = make_grid(_resolve_bounds(field, bounds), resolution)
    values = evaluate_grid_points(
        field, grid, _all_points(grid.shape), chunk_size, field_device(field, device), progress, "sample_grid"
    ).reshape(grid.shape)
    corners = np.stack([grid.origin, grid.origin + np.array(grid.cells) * grid.spacing])
    samples = GridSamples(torch.from_numpy(values), torch.from_numpy(corners), float(grid.spacing))
    if path is not None:
        write_npz(path, {"values": values, "bounds": corners, "spacing": np.float64(grid.spacing)})
    return samples


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
    precision = np.float32 if float32_holds(float(np.abs(box).max()), pixel) else np.float64
    x = torch.from_numpy(points.reshape(-1, 3).astype(precision)).to(field_device(field, device))
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


__all__ = [
    "Grid", "GridSamples", "extract_mesh", "field_slice", "level_set", "make_grid", "marching_cubes",
    "sample_grid", "slice_image",
]


class NearPointsField(torch.nn.Module):
    """`field` evaluated only within about `distance` of `points` (cells of an occupancy grid of that
    size, dilated by one); elsewhere +`distance`. Extraction then meshes observed surfaces only (a room
    from depth frames), and never evaluates the network far from the data.

    field: world x[..., 3] -> f[...]; points: Float[Tensor, "n 3"] world; distance: world units.
    """

    def __init__(self, field: Field, points: Tensor, distance: float):
        super().__init__()
        if not distance > 0:
            raise ConfigError(f"distance must be positive (world units), got {distance}")
        self.field, self.distance = field, float(distance)
        points = points.detach().double().cpu()
        self.origin = points.min(0).values - 2 * distance
        cells = ((points - self.origin) / distance).long()
        shape = (cells.max(0).values + 3).tolist()
        occupied = torch.zeros(shape, dtype=torch.bool)
        occupied[cells[:, 0], cells[:, 1], cells[:, 2]] = True
        occupied = torch.nn.functional.max_pool3d(occupied[None, None].float(), 3, 1, 1)[0, 0] > 0
        self.register_buffer("occupied", occupied, persistent=False)
        self.bounds = getattr(field, "bounds", None)

    def forward(self, x: Tensor) -> Tensor:
        cells = ((x.detach().double() - self.origin.to(x.device)) / self.distance).long()
        size = torch.tensor(self.occupied.shape, device=x.device)
        inside = ((cells >= 0) & (cells < size)).all(-1)
        near = torch.zeros(x.shape[:-1], dtype=torch.bool, device=x.device)
        c = cells[inside]
        near[inside] = self.occupied.to(x.device)[c[:, 0], c[:, 1], c[:, 2]]
        values = torch.full(x.shape[:-1], self.distance, dtype=torch.float32, device=x.device)
        if near.any():
            values[near] = self.field(x[near]).to(values.dtype)
        return values
