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
        offsets = torch.tensor([0, *sizes]).cumsum(0)
        self.table = nn.Parameter(init_scale * (2 * torch.rand(int(offsets[-1]), features_per_level) - 1))
        # per level: resolution, table rows, first row, hashed or dense (shaped to broadcast over [n, L, 8])
        self.register_buffer("resolution", torch.tensor(resolutions)[:, None], persistent=False)
        self.register_buffer("size", torch.tensor(sizes)[:, None], persistent=False)
        self.register_buffer("offset", offsets[:-1, None], persistent=False)
        self.register_buffer("hashed", torch.tensor([(r + 1) ** 3 > table for r in resolutions])[:, None],
                             persistent=False)
        corners = torch.tensor([[i >> 2 & 1, i >> 1 & 1, i & 1] for i in range(8)])
        self.register_buffer("corners", corners, persistent=False)

    def _rows(self, corner: Tensor) -> Tensor:
        """Int[Tensor, "n L 8 3"] integer grid corners -> Int[Tensor, "n L 8"] table rows."""
        i, j, k = corner.unbind(-1)
        dense = (i * (self.resolution + 1) + j) * (self.resolution + 1) + k
        hashed = (i * _PRIMES[0] ^ j * _PRIMES[1] ^ k * _PRIMES[2]) % self.size
        return torch.where(self.hashed, hashed, dense) + self.offset

    def forward(self, x: Tensor) -> Tensor:
        """x[..., 3] in [-bound, bound] (clamped outside) -> [..., out_dim]."""
        flat = x.reshape(-1, 3)
        u = (flat.clamp(-self.bound, self.bound) + self.bound) / (2 * self.bound)
        position = u[:, None, :] * self.resolution  # [n, L, 3]
        cell = position.detach().floor().minimum(self.resolution - 1)
        frac = position - cell  # differentiable in x
        corner = cell.long()[:, :, None, :] + self.corners  # [n, L, 8, 3]
        w = torch.stack([1 - frac, frac], dim=-1)  # [n, L, 3, 2]: weights of the low and high corner
        weight = (w[:, :, 0, :, None, None] * w[:, :, 1, None, :, None] * w[:, :, 2, None, None, :]).flatten(2)
        rows = self._rows(corner)
        # one gather for all levels, [n, L, 8, F]; index_select's backward (index_add_) is deterministic
        # on a CPU, where indexing's backward adds with atomics in thread order
        values = self.table.index_select(0, rows.reshape(-1)).reshape(*rows.shape, -1)
        features = (weight[..., None] * values).sum(-2).flatten(1)  # [n, L * F]
        return torch.cat([flat, features], dim=-1).reshape(*x.shape[:-1], self.out_dim)

