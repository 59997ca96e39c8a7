"""Occupancy Networks (Mescheder et al. 2019): a PointNet encoder with ResNet blocks maps a point
cloud to a code c; a decoder with conditional batch normalisation maps (x, c) to an occupancy logit.

With `plane_dim > 0` the encoder also writes three feature planes (Convolutional Occupancy Networks,
Peng et al. 2020): point features averaged into the xy, xz and yz cells of a `plane_resolution`^2 grid,
smoothed by a small U-Net, read back bilinearly at each query point and added to the decoder's blocks
(the global code still drives its conditional batch norms). The code is then one flat vector:
[global code (c_dim), planes (3 * plane_dim * plane_resolution^2)].

The network's field is `logit(threshold) - logit(x)`: negative inside, zero where the occupancy
probability equals `threshold` (0.5: the field is -logit), so the extraction at level 0 serves it
like an SDF. Complete a shape from a cloud with one forward pass: `model.field_from_cloud(points)`.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor, nn

from neuralsurf.errors import ConfigError, InputError
from neuralsurf.models.field import NormalizedField
from neuralsurf.models.spec import rebuildable
from neuralsurf.structures import Normalization


class ResnetBlockFC(nn.Module):
    """x + fc_1(relu(fc_0(relu(x)))), with a linear shortcut when the sizes differ; fc_1 starts at 0."""

    def __init__(self, size_in: int, size_out: int | None = None, size_h: int | None = None):
        super().__init__()
        size_out = size_in if size_out is None else size_out
        size_h = min(size_in, size_out) if size_h is None else size_h
        self.fc_0 = nn.Linear(size_in, size_h)
        self.fc_1 = nn.Linear(size_h, size_out)
        self.shortcut = None if size_in == size_out else nn.Linear(size_in, size_out, bias=False)
        nn.init.zeros_(self.fc_1.weight)

    def forward(self, x: Tensor) -> Tensor:
        dx = self.fc_1(torch.relu(self.fc_0(torch.relu(x))))
        return (x if self.shortcut is None else self.shortcut(x)) + dx


def plane_coordinates(points: Tensor, half: float) -> Tensor:
    """points Float[Tensor, "b n 3"] in [-half, half]^3 -> their xy, xz, yz coordinates in [-1, 1],
    Float[Tensor, "b 3 n 2"] (clamped: points outside the box read the border cells)."""
    uv = points[..., [[0, 1], [0, 2], [1, 2]]] / half
    return uv.clamp(-1, 1).permute(0, 2, 1, 3)


def plane_cells(points: Tensor, resolution: int, half: float) -> Tensor:
    """points Float[Tensor, "b n 3"] -> Long[Tensor, "b 3 n"]: the row-major index (v * resolution + u)
    of each point's cell on the three planes, the cells `grid_sample` reads at those coordinates."""
    uv = plane_coordinates(points, half)
    ij = ((uv + 1) / 2 * resolution).long().clamp(0, resolution - 1)
    return ij[..., 1] * resolution + ij[..., 0]


def plane_means(features: Tensor, cells: Tensor, resolution: int) -> Tensor:
    """features Float[Tensor, "b n c"], cells Long[Tensor, "b 3 n"] -> the mean feature of each cell of
    each plane, Float[Tensor, "b 3 r*r c"] (0 in empty cells)."""
    b, n, c = features.shape
    flat = (cells + torch.arange(b * 3, device=cells.device).view(b, 3, 1) * resolution ** 2).reshape(-1)
    sums = features.new_zeros(b * 3 * resolution ** 2, c).index_add_(
        0, flat, features[:, None].expand(b, 3, n, c).reshape(-1, c))
    counts = features.new_zeros(b * 3 * resolution ** 2).index_add_(0, flat, features.new_ones(flat.shape))
    return (sums / counts.clamp(min=1)[:, None]).view(b, 3, resolution ** 2, c)


def local_pool(features: Tensor, cells: Tensor, resolution: int) -> Tensor:
    """features Float[Tensor, "b n c"] -> Float[Tensor, "b n c"]: for each point, the sum over the three
    planes of the mean feature of its cell (ConvONet's local pooling)."""
    means = plane_means(features, cells, resolution)
    index = cells[..., None].expand(*cells.shape, features.shape[-1])
    return means.gather(2, index).sum(1)


def sample_planes(planes: Tensor, points: Tensor, half: float) -> Tensor:
    """planes Float[Tensor, "b 3 c r r"] (rows v, columns u), points Float[Tensor, "b t 3"] ->
    Float[Tensor, "b t c"]: the bilinear reads of the three planes at the points, summed."""
    b, _, c, r, _ = planes.shape
    grid = plane_coordinates(points, half).reshape(b * 3, 1, -1, 2)
    read = nn.functional.grid_sample(planes.reshape(b * 3, c, r, r), grid, mode="bilinear",
                                     padding_mode="border", align_corners=False)
    return read.view(b, 3, c, -1).sum(1).transpose(1, 2)


class PlaneUNet(nn.Module):
    """features[m, c, r, r] -> [m, c, r, r]: a small U-Net, two 3x3 convolutions a level, `depth`
    halvings of the resolution (r divisible by 2^depth), `channels` wide throughout."""

    def __init__(self, channels: int, depth: int = 2):
        super().__init__()

        def level(inputs: int) -> nn.Sequential:
            return nn.Sequential(nn.Conv2d(inputs, channels, 3, padding=1), nn.ReLU(),
                                 nn.Conv2d(channels, channels, 3, padding=1), nn.ReLU())

        self.down = nn.ModuleList(level(channels) for _ in range(depth + 1))
        self.up = nn.ModuleList(level(2 * channels) for _ in range(depth))
        self.out = nn.Conv2d(channels, channels, 1)

    def forward(self, x: Tensor) -> Tensor:
        skips = []
        for i, block in enumerate(self.down):
            x = block(x if i == 0 else nn.functional.max_pool2d(x, 2))
            skips.append(x)
        skips.pop()
        for block in self.up:
            x = block(torch.cat([nn.functional.interpolate(x, scale_factor=2.0), skips.pop()], dim=1))
        return self.out(x)


@rebuildable
class PointNetEncoder(nn.Module):
    """OccNet's ResnetPointnet: points[b, n, 3] -> code[b, c_dim]. Five ResNet blocks; after each
    (but the last) the features are max-pooled over the points and concatenated to every point.
    With `plane_dim > 0` (ConvONet's local pooling): pooled over each point's cells on three planes
    instead, and the code is [b, c_dim + 3 * plane_dim * plane_resolution^2]: the global code and the
    feature planes (U-Net over the cell means of the last features) of the points in [-half, half]^3."""

    def __init__(self, c_dim: int = 128, hidden: int = 128, blocks: int = 5, plane_dim: int = 0,
                 plane_resolution: int = 32, half: float = 0.55, unet_depth: int = 2):
        super().__init__()
        if min(c_dim, hidden, blocks) < 1:
            raise ConfigError(f"PointNetEncoder needs c_dim, hidden, blocks >= 1, got {c_dim}, {hidden}, {blocks}")
        if plane_dim and plane_resolution % 2 ** unet_depth:
            raise ConfigError(f"plane_resolution {plane_resolution} must be divisible by 2^unet_depth = "
                              f"{2 ** unet_depth}")
        self.layout = code_layout(c_dim, plane_dim, plane_resolution, half)
        self.fc_pos = nn.Linear(3, 2 * hidden)
        self.blocks = nn.ModuleList(ResnetBlockFC(2 * hidden, hidden) for _ in range(blocks))
        self.fc_c = nn.Linear(hidden, c_dim)
        if plane_dim:
            self.fc_plane = nn.Linear(hidden, plane_dim)
            self.unet = PlaneUNet(plane_dim, unet_depth)

    def forward(self, points: Tensor) -> Tensor:
        if points.ndim != 3 or points.shape[-1] != 3 or points.shape[1] < 1:
            raise InputError(f"PointNetEncoder expects clouds of shape (batch, n >= 1, 3), got {tuple(points.shape)}")
        _, plane_dim, resolution, half = self.layout
        cells = plane_cells(points, resolution, half) if plane_dim else None
        net = self.blocks[0](self.fc_pos(points))
        for block in self.blocks[1:]:
            pooled = (local_pool(net, cells, resolution) if plane_dim
                      else net.amax(dim=1, keepdim=True).expand_as(net))
            net = block(torch.cat([net, pooled], dim=-1))
        code = self.fc_c(torch.relu(net.amax(dim=1)))
        if not plane_dim:
            return code
        b = len(points)
        means = plane_means(self.fc_plane(net), cells, resolution)            # [b, 3, r*r, plane_dim]
        planes = means.transpose(2, 3).reshape(b * 3, plane_dim, resolution, resolution)
        return torch.cat([code, self.unet(planes).reshape(b, -1)], dim=-1)


class CodeLayout(NamedTuple):
    """What an encoder's code holds, which its decoder must read alike: a global code of `c_dim`
    entries, then three planes of `plane_dim` x `resolution`^2 over [-half, half]^3 (0s: none)."""

    c_dim: int
    plane_dim: int
    resolution: int
    half: float

    @property
    def size(self) -> int:
        """The entries of one flat code."""
        return self.c_dim + 3 * self.plane_dim * self.resolution ** 2


def code_layout(c_dim: int, plane_dim: int, plane_resolution: int, half: float) -> CodeLayout:
    """The checked `CodeLayout` of a code with these settings (the plane entries 0 without planes)."""
    if plane_dim < 0 or (plane_dim and (plane_resolution < 2 or half <= 0)):
        raise ConfigError(f"feature planes need plane_dim >= 0, plane_resolution >= 2 and half > 0, got "
                          f"{plane_dim}, {plane_resolution}, {half}")
    return CodeLayout(c_dim, plane_dim, plane_resolution, half) if plane_dim else CodeLayout(c_dim, 0, 0, 0.0)


class ConditionalBatchNorm(nn.Module):
    """x[b, t, f], c[b, c_dim] -> gamma(c) * BN(x) + beta(c) (de Vries et al. 2017), BN without affine
    parameters over the b * t rows; gamma starts at 1 and beta at 0."""

    def __init__(self, c_dim: int, features: int, momentum: float = 0.1):
        super().__init__()
        self.gamma = nn.Linear(c_dim, features)
        self.beta = nn.Linear(c_dim, features)
        self.bn = nn.BatchNorm1d(features, affine=False, momentum=momentum)
        nn.init.zeros_(self.gamma.weight)
        nn.init.ones_(self.gamma.bias)
        nn.init.zeros_(self.beta.weight)
        nn.init.zeros_(self.beta.bias)

    def forward(self, x: Tensor, c: Tensor) -> Tensor:
        b, t, f = x.shape
        normed = self.bn(x.reshape(b * t, f)).reshape(b, t, f)
        return self.gamma(c)[:, None, :] * normed + self.beta(c)[:, None, :]


class ConditionalResnetBlock(nn.Module):
    """OccNet's CResnetBlockConv1d: x + fc_1(relu(CBN_1(fc_0(relu(CBN_0(x, c))), c)))."""

    def __init__(self, c_dim: int, size: int):
        super().__init__()
        self.bn_0 = ConditionalBatchNorm(c_dim, size)
        self.bn_1 = ConditionalBatchNorm(c_dim, size)
        self.fc_0 = nn.Linear(size, size)
        self.fc_1 = nn.Linear(size, size)
        nn.init.zeros_(self.fc_1.weight)

    def forward(self, x: Tensor, c: Tensor) -> Tensor:
        net = self.fc_0(torch.relu(self.bn_0(x, c)))
        return x + self.fc_1(torch.relu(self.bn_1(net, c)))


@rebuildable
class CBNDecoder(nn.Module):
    """OccNet's DecoderCBatchNorm: x[b, t, 3], code[b, c_dim] -> occupancy logits[b, t]. With
    `plane_dim > 0` the code also holds feature planes (`PointNetEncoder`), read at x and added,
    through one linear layer each, to the input of every block (ConvONet's decoder)."""

    def __init__(self, c_dim: int = 128, hidden: int = 256, blocks: int = 5, plane_dim: int = 0,
                 plane_resolution: int = 32, half: float = 0.55):
        super().__init__()
        if min(c_dim, hidden, blocks) < 1:
            raise ConfigError(f"CBNDecoder needs c_dim, hidden, blocks >= 1, got {c_dim}, {hidden}, {blocks}")
        self.layout = code_layout(c_dim, plane_dim, plane_resolution, half)
        self.fc_p = nn.Linear(3, hidden)
        self.fc_planes = nn.ModuleList(nn.Linear(plane_dim, hidden) for _ in range(blocks if plane_dim else 0))
        self.blocks = nn.ModuleList(ConditionalResnetBlock(c_dim, hidden) for _ in range(blocks))
        self.bn = ConditionalBatchNorm(c_dim, hidden)
        self.fc_out = nn.Linear(hidden, 1)

    def forward(self, x: Tensor, code: Tensor) -> Tensor:
        c_dim, plane_dim, resolution, half = self.layout
        c, net = code[:, :c_dim], self.fc_p(x)
        local = (sample_planes(code[:, c_dim:].reshape(len(code), 3, plane_dim, resolution, resolution), x, half)
                 if plane_dim else None)
        for i, block in enumerate(self.blocks):
            net = block(net if local is None else net + self.fc_planes[i](local), c)
        return self.fc_out(torch.relu(self.bn(net, c)))[..., 0]


@rebuildable
class OccupancyNetwork(nn.Module):
    """Encoder + conditional decoder. `encode(cloud)` -> code, `logits(x, code)` for training,
    `forward(x[..., 3], code)` -> field (negative inside) for extraction."""

    def __init__(self, encoder: nn.Module, decoder: nn.Module, threshold: float = 0.5):
        super().__init__()
        if not 0 < threshold < 1:
            raise ConfigError(f"threshold is an occupancy probability in (0, 1), got {threshold}")
        if getattr(encoder, "layout", None) != getattr(decoder, "layout", None):
            raise ConfigError(f"the encoder writes codes of layout {getattr(encoder, 'layout', None)}, the decoder "
                              f"reads {getattr(decoder, 'layout', None)}; give both the same settings")
        self.encoder = encoder
        self.decoder = decoder
        self.threshold = float(threshold)
        self.latent_dim = encoder.layout.size

    def encode(self, cloud: Tensor) -> Tensor:
        """Float[Tensor, "b n 3"] (or "n 3") unit-frame points -> codes Float[Tensor, "b latent_dim"]."""
        return self.encoder(cloud[None] if cloud.ndim == 2 else cloud)

    def logits(self, x: Tensor, code: Tensor) -> Tensor:
        """x Float[Tensor, "b t 3"], code Float[Tensor, "b latent_dim"] -> occupancy logits [b, t]."""
        return self.decoder(x, code)

    def forward(self, x: Tensor, latent: Tensor | None = None) -> Tensor:
        """x[..., 3] (all points of one shape), latent[latent_dim] or [1, latent_dim] -> field[...], negative inside."""
        if latent is None:
            raise InputError("an occupancy network needs the code of a shape: encode a cloud "
                             "(model.encode(points)) and pass it, or use model.field_from_cloud(points)")
        if x.shape[-1] != 3:
            raise InputError(f"OccupancyNetwork expects points of shape (..., 3), got {tuple(x.shape)}")
        code = latent.reshape(1, -1)
        logits = self.decoder(x.reshape(1, -1, 3), code).reshape(x.shape[:-1])
        return math.log(self.threshold / (1 - self.threshold)) - logits

    @torch.no_grad()
    def field_from_cloud(self, points: Tensor, normalization=None, margin: float = 0.05):
        """Shape completion in one forward pass: the world-frame field of the shape whose (partial,
        noisy) surface points are `points` (Float[Tensor, "n 3"], in the frame the network was trained
        in unless `normalization` maps world to it). The model is put in eval mode. With feature planes,
        give as many points as the training clouds had: the planes' cells fill with the density."""
        points = torch.as_tensor(points, dtype=torch.float64)
        if points.ndim != 2 or points.shape[-1] != 3 or len(points) == 0:
            raise InputError(f"field_from_cloud takes a cloud of shape (n >= 1, 3), got {tuple(points.shape)}")
        if not torch.isfinite(points).all():
            raise InputError(f"the cloud holds NaN or inf in {int((~torch.isfinite(points).all(-1)).sum())} of its "
                             f"{len(points)} points; drop them first")
        normalization = normalization or Normalization()
        self.eval()
        device = next(self.parameters()).device
        unit = normalization.to_unit(points).float().to(device)
        code = self.encode(unit)[0]
        return NormalizedField(self, normalization, latent=code, margin=margin).eval()
