"""Occupancy Networks (Mescheder et al. 2019): a PointNet encoder with ResNet blocks maps a point
cloud to a code c; a decoder with conditional batch normalisation maps (x, c) to an occupancy logit.

The network's field is `logit(threshold) - logit(x)`: negative inside, zero where the occupancy
probability equals `threshold` (0.5: the field is -logit), so the extraction at level 0 serves it
like an SDF. Complete a shape from a cloud with one forward pass: `model.field_from_cloud(points)`.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from neuralsurf.errors import ConfigError, InputError
from neuralsurf.models.spec import rebuildable


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


@rebuildable
class PointNetEncoder(nn.Module):
    """OccNet's ResnetPointnet: points[b, n, 3] -> code[b, c_dim]. Five ResNet blocks; after each
    (but the last) the features are max-pooled over the points and concatenated to every point."""

    def __init__(self, c_dim: int = 128, hidden: int = 128, blocks: int = 5):
        super().__init__()
        if min(c_dim, hidden, blocks) < 1:
            raise ConfigError(f"PointNetEncoder needs c_dim, hidden, blocks >= 1, got {c_dim}, {hidden}, {blocks}")
        self.c_dim = c_dim
        self.fc_pos = nn.Linear(3, 2 * hidden)
        self.blocks = nn.ModuleList(ResnetBlockFC(2 * hidden, hidden) for _ in range(blocks))
        self.fc_c = nn.Linear(hidden, c_dim)

    def forward(self, points: Tensor) -> Tensor:
        if points.ndim != 3 or points.shape[-1] != 3 or points.shape[1] < 1:
            raise InputError(f"PointNetEncoder expects clouds of shape (batch, n >= 1, 3), got {tuple(points.shape)}")
        net = self.blocks[0](self.fc_pos(points))
        for block in self.blocks[1:]:
            pooled = net.amax(dim=1, keepdim=True).expand_as(net)
            net = block(torch.cat([net, pooled], dim=-1))
        return self.fc_c(torch.relu(net.amax(dim=1)))


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
    """OccNet's DecoderCBatchNorm: x[b, t, 3], c[b, c_dim] -> occupancy logits[b, t]."""

    def __init__(self, c_dim: int = 128, hidden: int = 256, blocks: int = 5):
        super().__init__()
        if min(c_dim, hidden, blocks) < 1:
            raise ConfigError(f"CBNDecoder needs c_dim, hidden, blocks >= 1, got {c_dim}, {hidden}, {blocks}")
        self.c_dim = c_dim
        self.fc_p = nn.Linear(3, hidden)
        self.blocks = nn.ModuleList(ConditionalResnetBlock(c_dim, hidden) for _ in range(blocks))
        self.bn = ConditionalBatchNorm(c_dim, hidden)
        self.fc_out = nn.Linear(hidden, 1)

    def forward(self, x: Tensor, c: Tensor) -> Tensor:
        net = self.fc_p(x)
        for block in self.blocks:
            net = block(net, c)
        return self.fc_out(torch.relu(self.bn(net, c)))[..., 0]


@rebuildable
class OccupancyNetwork(nn.Module):
    """Encoder + conditional decoder. `encode(cloud)` -> code, `logits(x, code)` for training,
    `forward(x[..., 3], code)` -> field (negative inside) for extraction."""

    def __init__(self, encoder: nn.Module, decoder: nn.Module, threshold: float = 0.5):
        super().__init__()
        if not 0 < threshold < 1:
            raise ConfigError(f"threshold is an occupancy probability in (0, 1), got {threshold}")
        if getattr(encoder, "c_dim", None) != getattr(decoder, "c_dim", None):
            raise ConfigError(f"the encoder's codes have {getattr(encoder, 'c_dim', None)} entries, the decoder "
                              f"takes {getattr(decoder, 'c_dim', None)}; give both the same c_dim")
        self.encoder = encoder
        self.decoder = decoder
        self.threshold = float(threshold)
        self.latent_dim = encoder.c_dim

    def encode(self, cloud: Tensor) -> Tensor:
        """Float[Tensor, "b n 3"] (or "n 3") unit-frame points -> codes Float[Tensor, "b c_dim"]."""
        return self.encoder(cloud[None] if cloud.ndim == 2 else cloud)

    def logits(self, x: Tensor, code: Tensor) -> Tensor:
        """x Float[Tensor, "b t 3"], code Float[Tensor, "b c_dim"] -> occupancy logits [b, t]."""
        return self.decoder(x, code)

    def forward(self, x: Tensor, latent: Tensor | None = None) -> Tensor:
        """x[..., 3] (all points of one shape), latent[c_dim] or [1, c_dim] -> field[...], negative inside."""
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
        in unless `normalization` maps world to it). The model is put in eval mode."""
        from neuralsurf.models.field import NormalizedField
        from neuralsurf.structures import Normalization

        normalization = normalization or Normalization()
        self.eval()
        device = next(self.parameters()).device
        unit = normalization.to_unit(torch.as_tensor(points, dtype=torch.float64)).float().to(device)
        code = self.encode(unit)[0]
        return NormalizedField(self, normalization, latent=code, margin=margin).eval()
