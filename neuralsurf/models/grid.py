"""A signed distance field stored on a sparse voxel grid: values at the grid points of the blocks that
depth frames observed, trilinearly interpolated (the layout of a sparse TSDF volume).

Grid point (i, j, k) lies at origin + (i, j, k) * voxel (unit frame); only the observed points hold a
value (`rows`: each point's row of `values`, -1 where none). A query averages the observed corners of its
cell with their trilinear weights (so unobserved points, which may lie in free space or behind a surface,
invent no zero crossing) and reads `outside` where no corner is observed. Initialised from a fused TSDF
(`from_observed`), the field starts at TSDF's answer; it is linear in its values (`corners`), so they can be
fitted by one least-squares solve (`solve_values`: to depth rays in `rooms`, to oriented points in
`observations.start`) as well as by `fit`.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable

import torch
from torch import Tensor, nn

from neuralsurf.errors import ConfigError
from neuralsurf.models.spec import rebuildable


@rebuildable
class VoxelSDF(nn.Module):
    """Unit-frame x[..., 3] -> signed distance [...]: trilinear in the observed values of a sparse voxel grid
    (see the module docstring).

    Args:
        shape: grid points per axis.
        origin: unit-frame position of grid point (0, 0, 0).
        voxel: grid spacing, unit frame.
        n_observed: grid points that hold a value (all of them: the values in grid order, the row index not stored).
        outside: the value where no corner of a query's cell is observed (free space, unit frame).
    """

    def __init__(self, shape: list[int], origin: list[float], voxel: float, n_observed: int, outside: float = 0.05):
        super().__init__()
        shape, origin = [int(s) for s in shape], [float(o) for o in origin]
        if len(shape) != 3 or len(origin) != 3 or any(s < 2 for s in shape) or not voxel > 0 or n_observed < 1:
            raise ConfigError(f"VoxelSDF needs 3 grid sizes >= 2, 3 origin coordinates, voxel > 0 and n_observed >= 1; "
                              f"got shape={shape}, origin={origin}, voxel={voxel}, n_observed={n_observed}")
        self.shape, self.voxel, self.outside = shape, float(voxel), float(outside)
        self.register_buffer("origin", torch.tensor(origin, dtype=torch.float32))
        self.values = nn.Parameter(torch.full((n_observed, 1), float(outside)))
        rows = torch.arange(n_observed, dtype=torch.int32).reshape(shape) if self.whole else torch.full(
            shape, -1, dtype=torch.int32)
        self.register_buffer("rows", rows, persistent=not self.whole)
        corner = torch.tensor([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
        self.register_buffer("steps", (corner[:, 0] * shape[1] + corner[:, 1]) * shape[2] + corner[:, 2],
                             persistent=False)
        # the last cell's index per axis, kept on the values' device (a CUDA graph cannot copy it there in a step)
        self.register_buffer("last", torch.tensor(shape) - 1, persistent=False)

    @property
    def whole(self) -> bool:
        """Every grid point observed: the values are in grid order, and the row index follows (not stored)."""
        return len(self.values) == self.shape[0] * self.shape[1] * self.shape[2]

    @classmethod
    def from_grid(cls, values: Tensor, observed: Tensor, origin, voxel: float, outside: float | None = None) -> VoxelSDF:
        """The field of dense grid values Float[Tensor, "X Y Z"] (unit frame) where Bool[Tensor, "X Y Z"]
        `observed`, point (0, 0, 0) at `origin` (3 unit-frame coordinates), spaced `voxel`. `outside`:
        default the largest observed value."""
        if values.shape != observed.shape or values.dim() != 3:
            raise ConfigError(f"VoxelSDF.from_grid needs values and observed of one shape X Y Z, got "
                              f"{tuple(values.shape)} and {tuple(observed.shape)}")
        if bool(observed.all()):  # a whole grid: its values are in grid order already
            model = cls(list(values.shape), [float(o) for o in origin], voxel, values.numel(),
                        float(values.max()) if outside is None else float(outside))
            with torch.no_grad():
                model.values[:, 0] = values.reshape(-1).float().cpu()
            return model
        linear = observed.reshape(-1).nonzero()[:, 0]
        if not len(linear):
            raise ConfigError("VoxelSDF.from_grid: no grid point is observed; fuse frames that see the surface first")
        chosen = values.reshape(-1)[linear]
        outside = float(chosen.max()) if outside is None else float(outside)
        return cls.from_observed(list(values.shape), linear, chosen, origin, voxel, outside)

    @classmethod
    def from_observed(cls, shape: list[int], linear: Tensor, values: Tensor, origin, voxel: float,
                      outside: float) -> VoxelSDF:
        """The field of a sparse grid of `shape`: values Float[Tensor, "n"] (unit frame) at the grid points of
        Int64[Tensor, "n"] `linear` indices (i-major, distinct), point (0, 0, 0) at `origin`, spaced `voxel`."""
        if linear.shape != values.shape or linear.dim() != 1:
            raise ConfigError(f"VoxelSDF.from_observed needs linear indices and values of one shape n, got "
                              f"{tuple(linear.shape)} and {tuple(values.shape)}")
        if not len(linear):
            raise ConfigError("VoxelSDF.from_observed: no grid point is observed; fuse frames that see the surface first")
        if len(linear) == shape[0] * shape[1] * shape[2]:  # a whole grid keeps its values in grid order
            values = torch.empty_like(values).index_copy_(0, linear, values)
        model = cls(list(shape), [float(o) for o in origin], voxel, len(linear), outside)
        with torch.no_grad():
            model.values[:, 0] = values.float().cpu()
            if not model.whole:  # a whole grid's rows are its grid order already
                model.rows.view(-1)[linear.cpu()] = torch.arange(len(linear), dtype=torch.int32)
        return model

    def corners(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """Float[Tensor, "n 3"] unit-frame queries -> (Long[Tensor, "n 8"] rows of `values` of each query's cell
        corners, i-major (0 where unobserved), Float[Tensor, "n 8"] their trilinear weights over the observed corners,
        summing to 1; all 0 where none is observed: such a query reads `outside`). The field is linear in `values`."""
        g = (x - self.origin) / self.voxel
        base = g.detach().floor()
        fraction = g - base
        base = base.long()
        inside = ((base >= 0) & (base < self.last)).all(-1)
        linear = torch.where(inside, (base[:, 0] * self.shape[1] + base[:, 1]) * self.shape[2] + base[:, 2], 0)
        wx, wy, wz = (torch.stack([1 - fraction[:, a], fraction[:, a]], -1) for a in range(3))
        w = (wx[:, :, None, None] * wy[:, None, :, None] * wz[:, None, None, :]).reshape(-1, 8)
        if self.whole:  # rows are grid order, every corner observed: no lookup, the weights are trilinear's own
            return linear[:, None] + self.steps, w * inside[:, None]
        row = self.rows.view(-1)[linear[:, None] + self.steps].long()
        w = w * ((row >= 0) & inside[:, None])
        total = w.sum(-1, keepdim=True)
        # a cell with some observed corners reads them alone
        return row.clamp_min(0), torch.where(total > 1e-6, w / total.clamp_min(1e-12), 0.0)

    def forward(self, x: Tensor, latent: Tensor | None = None) -> Tensor:
        """x Float[Tensor, "... 3"] unit frame -> Float[Tensor, "..."]."""
        if latent is not None:
            raise ConfigError("VoxelSDF is one shape's field; it takes no latent code")
        if self.whole and not (torch.is_grad_enabled() and (x.requires_grad or self.values.requires_grad)):
            return self.sampled(x)
        row, w = self.corners(x.reshape(-1, 3))
        value = torch.nn.functional.embedding(row, self.values)[..., 0]
        mixed = (w * value).sum(-1)
        result = torch.where(w.detach().sum(-1) > 0, mixed, torch.full_like(mixed, self.outside))
        return result.reshape(x.shape[:-1])

    def sampled(self, x: Tensor) -> Tensor:
        """x Float[Tensor, "... 3"] unit frame -> Float[Tensor, "..."]: `forward` on a whole grid by
        `grid_sample`'s trilinear interpolation (2.6x faster than the gathers of `corners`; no second derivative,
        so `forward` takes it only where no gradient is asked for)."""
        g = (x.reshape(-1, 3) - self.origin) / self.voxel
        inside = ((g >= 0) & (g < self.last)).all(-1)
        where = (2 * g / self.last - 1).flip(-1).view(1, 1, 1, -1, 3)  # grid_sample's (z, y, x) order in [-1, 1]
        value = torch.nn.functional.grid_sample(self.values.view(1, 1, *self.shape), where, align_corners=True)
        return torch.where(inside, value.view(-1), self.outside).reshape(x.shape[:-1])

    @torch.no_grad()
    def dense(self, start: int = 0, stop: int | None = None) -> tuple[Tensor, Tensor]:
        """(values Float[Tensor, "x Y Z"], observed Bool[Tensor, "x Y Z"]) of the grid points whose first index lies
        in [start, stop) (default: the whole grid; unit frame; `outside` where not observed)."""
        rows = self.rows[start:stop]
        observed = rows >= 0
        values = torch.full(rows.shape, self.outside, device=self.values.device)
        values[observed] = self.values[rows[observed].long(), 0]
        return values, observed


def grid_adjacency(coordinates: Tensor) -> Tensor:
    """Float sparse CSR [k, k]: 1 where two of Int[Tensor, "k 3"] distinct grid points, in grid order, are axis
    neighbours, with int32 indices: six entries a row, a missing neighbour's a 0 on the diagonal (no pass that drops
    them; products are the same). A product with it reads a fraction of the memory that a dense neighbour sum over
    the points' bounding box does: 5x faster on the bunny's start."""
    low = (coordinates.min(0).values - 1).tolist()  # a box one point wider each side: outside it reads "none"
    size = [high - first + 2 for high, first in zip(coordinates.max(0).values.tolist(), low)]
    if size[0] * size[1] * size[2] >= 2**31:
        raise ConfigError(f"grid_adjacency's points span {size} grid points, beyond int32 indices")
    at = coordinates.int()
    local = ((at[:, 0] - low[0]) * size[1] + at[:, 1] - low[1]) * size[2] + at[:, 2] - low[2]
    count, device = len(local), coordinates.device
    index = torch.full((size[0] * size[1] * size[2],), -1, dtype=torch.int32, device=device)
    index[local] = torch.arange(count, dtype=torch.int32, device=device)
    plane = size[1] * size[2]
    steps = torch.tensor([-plane, -size[2], -1, 1, size[2], plane], dtype=torch.int32, device=device)  # grid order
    neighbours = index.index_select(0, (local[:, None] + steps).view(-1)).view(count, 6)
    present = neighbours >= 0
    columns = torch.where(present, neighbours, torch.arange(count, dtype=torch.int32, device=device)[:, None])
    rows = torch.arange(0, 6 * count + 1, 6, dtype=torch.int32, device=device)
    with warnings.catch_warnings():  # "sparse CSR support is in beta": construction and products are all it needs
        warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta", category=UserWarning)
        warnings.filterwarnings("ignore", message="Sparse invariant checks are implicitly disabled", category=UserWarning)
        return torch.sparse_csr_tensor(rows, columns.view(-1), present.view(-1).float(), (count, count),
                                       check_invariants=False)  # valid as built


def neighbour_sum(grid: Tensor) -> Tensor:
    """Float[Tensor, "x y z"]: each grid point's sum of its axis neighbours' values in Float[Tensor, "x y z"] `grid`
    (fewer neighbours on its faces)."""
    total = torch.zeros_like(grid)
    for axis in range(3):
        n = grid.shape[axis]
        total.narrow(axis, 0, n - 1).add_(grid.narrow(axis, 1, n - 1))
        total.narrow(axis, 1, n - 1).add_(grid.narrow(axis, 0, n - 1))
    return total


REFINEMENT_GAIN = 0.05
"""`solve_values` keeps a refinement pass only where it lowers its score by this share."""


@torch.no_grad()
def solve_values(model: VoxelSDF, points: Tensor, targets: Tensor, weights: Tensor, prior_weight: float = 10.0,
                 iterations: int = 5, chunk: int = 1 << 20, smoothness: float = 0.0,
                 unknowns: Tensor | None = None, refinements: int = 0, refinement_iterations: int | None = None,
                 score: Callable[[VoxelSDF], float] | None = None, score_below: float = math.inf) -> VoxelSDF:
    """`model` with its values v fitted to the equations model(points) = targets (Float[Tensor, "m 3"],
    Float[Tensor, "m"], weighted by Float[Tensor, "m"]) and held to their start v0: the minimum of
    sum weights (A v - targets)^2 + lam |v - v0|^2 + mu sum over grid edges (v_i - v_j)^2, lam = `prior_weight` and
    mu = `smoothness` x the mean data weight of a value, by `iterations` steps of Jacobi-preconditioned conjugate
    gradients from v0. The membrane term (`smoothness` > 0) lets a value follow its neighbours where its start
    disagrees with them, so what the equations say spreads (as far as the iterations carry it) instead of each value
    keeping its start; it needs a whole grid (every point observed, as `observations.start` builds). Points with no
    observed corner are left out (the field reads `outside` there, whatever v).
    The unknowns are the values the equations read and Long[Tensor, "k"] rows `unknowns`; the others keep their
    start (as they would in the full system without smoothness), so the cost follows the equations, not the grid.
    With `refinements` > 0, the same system is then solved up to that many times more for a correction from the
    equations' residual alone (iterated Tikhonov), by `refinement_iterations` steps each (default `iterations`): each
    pass takes back most of the bias the prior and the membrane put on what the equations determine well, while what
    they leave undetermined stays held; with `score` (of the model, lower is better), the passes start only where the
    first solve scores below `score_below`, and a pass is kept only while it lowers the score by `REFINEMENT_GAIN`.
    `chunk`: points looked up at once (bounds memory, same result)."""
    refinement_iterations = iterations if refinement_iterations is None else refinement_iterations
    if not prior_weight > 0 or min(iterations, refinement_iterations, refinements) < 0 or not smoothness >= 0:
        raise ConfigError(f"solve_values needs prior_weight > 0, smoothness >= 0 and iterations, refinement_iterations "
                          f"and refinements >= 0, got {prior_weight}, {smoothness}, {iterations}, "
                          f"{refinement_iterations} and {refinements}")
    device = model.values.device
    rows, w, kept = [], [], []
    for start in range(0, len(points), chunk):  # the corners' temporaries are a few times rows' size
        r, c = model.corners(points[start : start + chunk].to(device))
        used = c.sum(-1) > 0
        rows.append(r[used].int())
        w.append(c[used])
        kept.append(used)
    rows, w, used = torch.cat(rows), torch.cat(w), torch.cat(kept)
    if not used.any():
        return model
    targets, weights = targets.to(device)[used], weights.to(device)[used]
    order = rows[:, 0].argsort()  # equations in grid order: the products' gathers and adds stay in cache (4x faster)
    rows, w, targets, weights = rows[order], w[order], targets[order], weights[order]
    read = rows.reshape(-1) if unknowns is None else torch.cat([rows.reshape(-1), unknowns.to(device).int()])
    touched, flat = torch.unique(read, return_inverse=True)
    flat = flat[: rows.numel()].int()  # index_add_ takes int32 indices: half the memory of the largest array
    start = model.values[touched, 0]

    def at_points(v: Tensor) -> Tensor:  # A v: the field at the equations' points (index_select: 3x v[rows]'s speed)
        return (w * v.index_select(0, flat).view(w.shape)).sum(-1)

    def gather(per_equation: Tensor) -> Tensor:  # A^T diag(weights) per_equation
        return torch.zeros_like(start).index_add_(0, flat, (w * (weights * per_equation)[:, None]).reshape(-1))

    diagonal = torch.zeros_like(start).index_add_(0, flat, (w * w * weights[:, None]).reshape(-1))
    scale = diagonal[diagonal > 0].mean()
    lam, mu = prior_weight * scale, smoothness * scale
    right = gather(targets) + lam * start
    if mu > 0:  # over a whole grid, whose rows are its grid order
        if not model.whole:
            raise ConfigError("solve_values' smoothness needs every grid point observed (a whole grid, as "
                              "VoxelSDF.from_grid with observed all true makes)")
        linear = touched.long()
        _, y, z = model.shape
        coordinates = torch.stack([touched // (y * z), touched // z % y, touched % z], -1)  # int32, as touched
        last = model.last.to(coordinates)
        if coordinates.min() > 0 and (coordinates.max(0).values < last).all():  # none on the grid's faces
            edges = 6.0  # grid neighbours of each value: a scalar spares a pass per product
        else:
            edges = ((coordinates > 0).sum(-1) + (coordinates < last).sum(-1)).to(start.dtype)
        held = model.values[:, 0].index_fill(0, linear, 0.0)  # the values kept at their start
        right += mu * neighbour_sum(held.view(model.shape)).view(-1)[linear]
        adjacency = grid_adjacency(coordinates).to(start.dtype)
    own = lam + mu * edges if mu > 0 else lam  # the prior's and the membrane's diagonal
    preconditioner = 1 / (diagonal + own)

    def normal(v: Tensor) -> Tensor:  # (A^T W A + lam + mu (edges - adjacency)) v
        product = gather(at_points(v)).add_(own * v)
        return product.sub_(adjacency @ v, alpha=float(mu)) if mu > 0 else product

    values = conjugate_gradients(normal, right, start.clone(), preconditioner, iterations)
    model.values[touched, 0] = values
    best = score(model) if score is not None and refinements else None
    if best is not None and not best < score_below:
        refinements = 0
    for _ in range(refinements):  # the same system, for a correction from what the equations still miss
        missed = gather(targets - at_points(values))
        refined = values + conjugate_gradients(normal, missed, None, preconditioner, refinement_iterations)
        model.values[touched, 0] = refined
        if best is not None:
            scored = score(model)
            if scored > (1 - REFINEMENT_GAIN) * best:
                model.values[touched, 0] = values
                break
            best = scored
        values = refined
    return model


def conjugate_gradients(product: Callable[[Tensor], Tensor], right: Tensor, values: Tensor | None,
                        preconditioner: Tensor, iterations: int) -> Tensor:
    """Float[Tensor, "k"]: `iterations` steps of preconditioned conjugate gradients on product(v) = right from
    `values` (updated in place; None: from zeros, which spares a product), `product` symmetric positive definite,
    `preconditioner` its inverse diagonal."""
    if values is None:
        values, residual = torch.zeros_like(right), right.clone()
    else:
        residual = right - product(values)
    z = preconditioner * residual
    direction, rz = z.clone(), float(residual.dot(z))
    converged = 1e-12 * rz  # float32 round-off beyond this: further steps would divide noise by noise
    for _ in range(iterations):
        if rz <= converged:
            break
        step_product = product(direction)
        step = rz / float(direction.dot(step_product))
        values.add_(direction, alpha=step)
        residual.sub_(step_product, alpha=step)
        torch.mul(preconditioner, residual, out=z)
        rz, previous = float(residual.dot(z)), rz
        direction.mul_(rz / previous).add_(z)
    return values
