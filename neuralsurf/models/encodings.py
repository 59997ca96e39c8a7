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


def _corners(x: Tensor, y: Tensor, z: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Three [..., 2] per-axis values -> views broadcasting to [..., 2, 2, 2] (x, y, z)."""
    return x[..., :, None, None], y[..., None, :, None], z[..., None, None, :]


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
        offsets = torch.tensor([0, *sizes]).cumsum(0)
        self.table = nn.Parameter(init_scale * (2 * torch.rand(int(offsets[-1]), features_per_level) - 1))
        # per level: resolution, table rows, first row, hashed or dense (shaped to broadcast over [n, L, 8])
        self.register_buffer("resolution", torch.tensor(resolutions)[:, None], persistent=False)
        self.register_buffer("size", torch.tensor(sizes)[:, None], persistent=False)
        self.register_buffer("offset", offsets[:-1, None], persistent=False)
        self.register_buffer("hashed", torch.tensor([(r + 1) ** 3 > table for r in resolutions])[:, None],
                             persistent=False)

    def _rows(self, low: Tensor) -> Tensor:
        """Int[Tensor, "n L 3"] low corners of the cells -> Int[Tensor, "n L 2 2 2"] table rows of the
        8 corners, indexed [x, y, z] by low (0) or high (1). Each axis's two coordinates are scaled
        (dense) or multiplied by its prime (hashed) once, then combined by broadcasting."""
        axes = torch.stack([low, low + 1], -1).unbind(-2)  # 3 x [n, L, 2]
        side = (self.resolution + 1)[..., None, None]
        i, j, k = _corners(*axes)
        dense = (i * side + j) * side + k
        i, j, k = _corners(*(a * prime for a, prime in zip(axes, _PRIMES)))
        hashed = (i ^ j ^ k) & (self.size - 1)[..., None, None]  # hashed tables have 2^k rows
        return torch.where(self.hashed[..., None, None], hashed, dense) + self.offset[..., None, None]

    def forward(self, x: Tensor) -> Tensor:
        """x[..., 3] in [-bound, bound] (clamped outside) -> [..., out_dim]."""
        flat = x.reshape(-1, 3)
        u = (flat.clamp(-self.bound, self.bound) + self.bound) / (2 * self.bound)
        position = u[:, None, :] * self.resolution  # [n, L, 3]
        cell = position.detach().floor().minimum(self.resolution - 1)
        frac = position - cell  # differentiable in x
        rows = self._rows(cell.long())  # [n, L, 2, 2, 2]
        # one gather for all levels; index_select's backward (index_add_) is deterministic on a CPU,
        # where indexing's backward adds with atomics in thread order
        v = self.table.index_select(0, rows.reshape(-1)).reshape(*rows.shape, -1)  # [n, L, 2, 2, 2, F]
        # trilinear interpolation as three lerps (x, then y, then z): less than half the work of
        # weighting all 8 corners, in the forward pass and in the eikonal term's double backward
        v = torch.lerp(v[:, :, 0], v[:, :, 1], frac[:, :, 0, None, None, None])  # [n, L, 2, 2, F]
        v = torch.lerp(v[:, :, 0], v[:, :, 1], frac[:, :, 1, None, None])  # [n, L, 2, F]
        features = torch.lerp(v[:, :, 0], v[:, :, 1], frac[:, :, 2, None]).flatten(1)  # [n, L * F]
        return torch.cat([flat, features], dim=-1).reshape(*x.shape[:-1], self.out_dim)
