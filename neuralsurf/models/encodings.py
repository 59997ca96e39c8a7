"""Input encodings of 3D points: x[..., 3] -> [x, features][..., out_dim].

Every encoding keeps the raw coordinates as its first three outputs, so that a geometric
initialisation of the network after it (zero weights on the features) starts from a sphere.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from neuralsurf.errors import ConfigError
from neuralsurf.models.spec import rebuildable


@rebuildable
class FourierFeatures(nn.Module):
    """NeRF-style positional encoding: [x, sin(2^k pi x), cos(2^k pi x)] for k < frequencies."""

    def __init__(self, frequencies: int = 6):
        super().__init__()
        if frequencies < 0:
            raise ConfigError(f"FourierFeatures needs frequencies >= 0, got {frequencies}")
        self.register_buffer("bands", math.pi * 2.0 ** torch.arange(frequencies), persistent=False)
        self.out_dim = 3 + 6 * frequencies

    def forward(self, x: Tensor) -> Tensor:
        """x[..., 3] -> [..., 3 + 6 * frequencies]."""
        angles = (x[..., None] * self.bands).flatten(-2)
        return torch.cat([x, torch.sin(angles), torch.cos(angles)], dim=-1)


# large primes of Teschner et al. (2003), as used by Instant-NGP's spatial hash
_PRIMES = (1, 2_654_435_761, 805_459_861)


@rebuildable
class HashGrid(nn.Module):
    """Multi-resolution grid of learned features (Instant-NGP, Mueller et al. 2022), pure PyTorch.

    Level l has resolution base * growth^l over the cube [-bound, bound]^3; a level whose
    (res + 1)^3 corners fit in the table is stored densely, finer levels are hashed. Features are
    trilinearly interpolated, so the encoding is differentiable twice in x (eikonal terms).
    """

    def __init__(
        self,
        levels: int = 8,
        features_per_level: int = 2,
        log2_table_size: int = 19,
        base_resolution: int = 16,
        max_resolution: int = 512,
        bound: float = 0.6,
        init_scale: float = 1e-4,
    ):
        super().__init__()
        if levels < 1 or base_resolution < 2 or max_resolution < base_resolution:
            raise ConfigError(
                f"HashGrid needs levels >= 1 and 2 <= base_resolution <= max_resolution, got "
                f"levels={levels}, base_resolution={base_resolution}, max_resolution={max_resolution}"
            )
        growth = (max_resolution / base_resolution) ** (1 / max(levels - 1, 1))
        resolutions = [int(round(base_resolution * growth**level)) for level in range(levels)]
        table = 2**log2_table_size
        sizes = [min((r + 1) ** 3, table) for r in resolutions]
        self.bound = bound
        self.out_dim = 3 + levels * features_per_level
        if sum(sizes) >= 2**31:
            raise ConfigError(f"HashGrid's {sum(sizes)} table rows exceed int32 indices; "
                              f"lower log2_table_size or levels")
        offsets = torch.tensor([0, *sizes]).cumsum(0)
        self.table = nn.Parameter(init_scale * (2 * torch.rand(sum(sizes), features_per_level) - 1))
        # per level (shaped to broadcast over [2, L, 3, n]): resolution, and what multiplies each
        # axis's corner coordinate: (side^2, side, 1) for a dense level, the primes for a hashed one,
        # reduced modulo the table size (the masked product is the same); levels grow finer, so the
        # dense ones come first. int32 where no product can overflow it.
        self.dense_levels = sum((r + 1) ** 3 <= table for r in resolutions)
        self.table_mask = table - 1  # hashed levels have 2^k rows
        axis_factors = [[(r + 1) ** 2, r + 1, 1] for r in resolutions[: self.dense_levels]]
        axis_factors += [[prime & self.table_mask for prime in _PRIMES]] * (levels - self.dense_levels)
        wide = (max(resolutions) + 1) * max(max(f) for f in axis_factors) >= 2**31
        self.register_buffer("resolution", torch.tensor(resolutions)[:, None, None], persistent=False)
        factors = torch.tensor(axis_factors, dtype=torch.int64 if wide else torch.int32)
        self.register_buffer("axis_factors", factors[..., None], persistent=False)
        self.register_buffer("offset", offsets[:-1, None].int(), persistent=False)

    def _rows(self, low: Tensor) -> Tensor:
        """Int[Tensor, "L 3 n"] low corners of the cells -> Int[Tensor, "n L 2 2 2"] table rows of the
        8 corners, indexed [x, y, z] by low (0) or high (1). Each axis's two coordinates are scaled
        (dense: row = x side^2 + y side + z) or multiplied by its prime (hashed: row = the products
        xor-ed and masked, Instant-NGP's hash) once, then combined by broadcasting with the points
        innermost (contiguous, vectorised: 2x faster than points outermost), then transposed in one
        copy: to int64 where autograd may run `index_select`'s backward (~30x slower with int32 rows),
        kept int32 without it (the encoding 20 % faster: extraction, held-out reads)."""
        axes = torch.stack([low, low + 1]) * self.axis_factors  # [2, L, 3, n]
        dense, hashed = axes.split([self.dense_levels, len(self.axis_factors) - self.dense_levels], 1)
        dense, hashed = dense.int().unbind(2), (hashed & self.table_mask).int().unbind(2)  # 3 x [2, L, n]
        offset = self.offset.split([self.dense_levels, len(self.offset) - self.dense_levels])
        dense_rows = (dense[0] + offset[0])[:, None, None] + dense[1][None, :, None] + dense[2][None, None, :]
        hashed_rows = (hashed[0][:, None, None] ^ hashed[1][None, :, None] ^ hashed[2][None, None, :]) + offset[1]
        rows = torch.cat([dense_rows, hashed_rows], 3)  # [2, 2, 2, L, n]
        kind = torch.int64 if torch.is_grad_enabled() else torch.int32
        return rows.permute(4, 3, 0, 1, 2).to(kind, memory_format=torch.contiguous_format)

    def forward(self, x: Tensor) -> Tensor:
        """x[..., 3] in [-bound, bound] (clamped outside) -> [..., out_dim]."""
        flat = x.reshape(-1, 3)
        u = (flat.clamp(-self.bound, self.bound) + self.bound) / (2 * self.bound)
        position = u.T * self.resolution  # [L, 3, n]
        cell = position.detach().floor().minimum(self.resolution - 1)
        frac = (position - cell).permute(2, 0, 1).contiguous()  # [n, L, 3], differentiable in x
        rows = self._rows(cell.int())  # [n, L, 2, 2, 2]
        # one gather for all levels, each point's 8 corners together (nearby rows: cache-friendly);
        # index_select's backward (index_add_) is deterministic on a CPU, where indexing's backward
        # adds with atomics in thread order
        v = self.table.index_select(0, rows.reshape(-1)).reshape(*rows.shape, -1)  # [n, L, 2, 2, 2, F]
        # trilinear interpolation as three lerps (x, then y, then z): less than half the work of
        # weighting all 8 corners, in the forward pass and in the eikonal term's double backward;
        # unbind, not indexing: its backward stacks the halves instead of filling zeros for each
        v = torch.lerp(*v.unbind(2), frac[:, :, 0, None, None, None])  # [n, L, 2, 2, F]
        v = torch.lerp(*v.unbind(2), frac[:, :, 1, None, None])  # [n, L, 2, F]
        v = torch.lerp(*v.unbind(2), frac[:, :, 2, None])  # [n, L, F]
        features = v.flatten(1)  # [n, L * F]
        return torch.cat([flat, features], dim=-1).reshape(*x.shape[:-1], self.out_dim)
