"""DeepSDF-style MLP (Park et al. 2019) with IGR's geometric initialisation (Gropp et al. 2020)."""

from __future__ import annotations

import math
from typing import Literal

import torch
from torch import Tensor, nn
from torch.nn.utils.parametrizations import weight_norm as apply_weight_norm

from neuralsurf.errors import ConfigError, InputError
from neuralsurf.models.spec import rebuildable


class Sine(nn.Module):
    """sin(omega * x), the SIREN activation (Sitzmann et al. 2020)."""

    def __init__(self, omega: float = 30.0):
        super().__init__()
        self.omega = omega

    def forward(self, x: Tensor) -> Tensor:
        return torch.sin(self.omega * x)


def _activation(name: str, softplus_beta: float, sine_omega: float) -> nn.Module:
    if name == "relu":
        return nn.ReLU()
    if name == "softplus":
        return nn.Softplus(beta=softplus_beta)
    if name == "sine":
        return Sine(sine_omega)
    raise ConfigError(f"unknown activation {name!r}; choose relu, softplus or sine")


@rebuildable
class SDFMLP(nn.Module):
    """x[..., 3] (unit frame) [+ latent code] -> signed distance [...].

    `depth` hidden layers of `width` units; the encoded input (and latent code) is concatenated
    again before each layer in `skip_layers`. With `geometric_init` the network starts as the
    SDF of a sphere of `init_radius` (relu/softplus only; sine uses SIREN's initialisation), with
    zero weights on encoding features and latent codes so they grow from that sphere.
    """

    def __init__(
        self,
        width: int = 256,
        depth: int = 8,
        skip_layers: tuple[int, ...] = (4,),
        activation: Literal["relu", "softplus", "sine"] = "softplus",
        softplus_beta: float = 100.0,
        sine_omega: float = 30.0,
        weight_norm: bool = True,
        geometric_init: bool = True,
        init_radius: float = 0.3,
        encoding: nn.Module | None = None,
        latent_dim: int = 0,
    ):
        super().__init__()
        if width < 1 or depth < 1:
            raise ConfigError(f"SDFMLP needs width >= 1 and depth >= 1, got width={width}, depth={depth}")
        bad_skips = [s for s in skip_layers if not 0 < s < depth]
        if bad_skips:
            raise ConfigError(f"skip_layers {bad_skips} must lie in 1..{depth - 1} (hidden layer indices)")
        self.encoding = encoding
        self.latent_dim = latent_dim
        self.skip_layers = tuple(skip_layers)
        self.activation = _activation(activation, softplus_beta, sine_omega)
        input_dim = (encoding.out_dim if encoding is not None else 3) + latent_dim
        self.layers = nn.ModuleList()
        for index in range(depth + 1):
            in_dim = input_dim if index == 0 else width
            out_dim = 1 if index == depth else width
            if index + 1 in self.skip_layers:  # this layer's output is concatenated with the input
                out_dim = width - input_dim
                if out_dim < 1:
                    raise ConfigError(f"width {width} must exceed the input size {input_dim} to use skips")
            self.layers.append(nn.Linear(in_dim, out_dim))
        if activation == "sine":
            self._siren_init(sine_omega)
        elif geometric_init:
            self._geometric_init(init_radius, input_dim)
        if weight_norm:
            for index, layer in enumerate(self.layers):
                self.layers[index] = apply_weight_norm(layer)

    def _geometric_init(self, radius: float, input_dim: int) -> None:
        """IGR's initialisation: f(x) ~ |x| - radius at the start."""
        for index, layer in enumerate(self.layers):
            w = layer.weight
            if index == len(self.layers) - 1:
                nn.init.normal_(w, mean=math.sqrt(math.pi) / math.sqrt(w.shape[1]), std=1e-4)
                nn.init.constant_(layer.bias, -radius)
                continue
            nn.init.normal_(w, 0.0, math.sqrt(2) / math.sqrt(w.shape[0]))
            nn.init.zeros_(layer.bias)
            if index == 0:
                nn.init.zeros_(w[:, 3:])  # only raw xyz at first: features and latent start silent
            elif index in self.skip_layers and input_dim > 3:
                nn.init.zeros_(w[:, -(input_dim - 3) :])

    def _siren_init(self, omega: float) -> None:
        with torch.no_grad():
            for index, layer in enumerate(self.layers):
                fan_in = layer.weight.shape[1]
                bound = 1 / fan_in if index == 0 else math.sqrt(6 / fan_in) / omega
                layer.weight.uniform_(-bound, bound)

    def forward(self, x: Tensor, latent: Tensor | None = None) -> Tensor:
        """x[..., 3], latent[..., latent_dim] or [latent_dim] -> sdf[...]."""
        if x.shape[-1] != 3:
            raise InputError(f"SDFMLP expects points of shape (..., 3), got {tuple(x.shape)}")
        inputs = self.encoding(x) if self.encoding is not None else x
        if self.latent_dim:
            if latent is None:
                raise InputError(f"this SDFMLP was built with latent_dim={self.latent_dim}; pass a latent code")
            inputs = torch.cat([inputs, latent.expand(*x.shape[:-1], self.latent_dim)], dim=-1)
        h = inputs
        for index, layer in enumerate(self.layers):
            if index in self.skip_layers:
                h = torch.cat([h, inputs], dim=-1) / math.sqrt(2)
            h = layer(h)
            if index < len(self.layers) - 1:
                h = self.activation(h)
        return h[..., 0]
