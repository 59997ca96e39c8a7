"""An MLP that refines a closed-form start: f(x) = start(x) + voxel * mlp(x).

The start is a `VoxelSDF` solved from the data before the fit (`observations.start.voxel_start` for oriented
points) and frozen; `fit` hands it over (`set_start`), which zeroes the MLP's output layer, so the fit begins at
the start and the network only learns what the start misses, in units of the start's voxel (so that the
optimiser's first steps move the surface by a fraction of a voxel, not of the box). Without a start (depth rays and the other
observations that offer none) the model is its `SDFMLP` alone, geometric initialisation included.
"""

from __future__ import annotations

from typing import Literal

import torch
from torch import Tensor, nn
from torch.nn.utils import parametrize

from neuralsurf.errors import ConfigError
from neuralsurf.models.grid import VoxelSDF
from neuralsurf.models.sdf_mlp import SDFMLP
from neuralsurf.models.spec import rebuildable


@rebuildable
class RefinedSDF(SDFMLP):
    """Unit-frame x[..., 3] -> start(x) + start.voxel * SDFMLP(x) [...]: `SDFMLP`'s arguments, and

    Args:
        start_resolution: the most cells per side of the start's grid over the fit's box (what `fit` asks the data for).
        start: the frozen start; None until `set_start` (then the MLP alone).
    """

    def __init__(
        self,
        width: int = 64,
        depth: int = 2,
        skip_layers: tuple[int, ...] = (),
        activation: Literal["relu", "softplus", "sine"] = "softplus",
        softplus_beta: float = 100.0,
        sine_omega: float = 30.0,
        weight_norm: bool = False,
        geometric_init: bool = True,
        init_radius: float = 0.3,
        encoding: nn.Module | None = None,
        latent_dim: int = 0,
        start_resolution: int = 256,
        start: VoxelSDF | None = None,
    ):
        super().__init__(width, depth, skip_layers, activation, softplus_beta, sine_omega, weight_norm, geometric_init,
                         init_radius, encoding, latent_dim)
        if not (isinstance(start_resolution, int) and start_resolution >= 8):
            raise ConfigError(f"RefinedSDF needs an integer start_resolution >= 8 (cells per side of its start), "
                              f"got {start_resolution!r}")
        if self.latent_dim:
            raise ConfigError("RefinedSDF refines one shape's start; it takes no latent code (latent_dim=0)")
        self.start_resolution = start_resolution
        self.start = None
        if start is not None:  # rebuilt from a checkpoint: its weights follow
            self.set_start(start, zero_output=False)

    def set_start(self, start: VoxelSDF, zero_output: bool = True) -> RefinedSDF:
        """Take `start` (frozen) as the field the MLP refines; with `zero_output` the MLP's output layer is zeroed,
        so the model equals `start` until trained."""
        if not isinstance(start, VoxelSDF):
            raise ConfigError(f"RefinedSDF's start is a VoxelSDF, got {type(start).__name__}")
        self.start = start.requires_grad_(False)
        arguments = self.__dict__.get("constructor_arguments")
        if arguments is not None:  # a checkpoint's spec rebuilds the start too
            arguments["start"] = start
        if zero_output:
            last = self.layers[-1]
            weight = last.parametrizations.weight.original0 if parametrize.is_parametrized(last, "weight") else last.weight
            with torch.no_grad():  # a weight-normed layer: its gain, not its direction (0 / |0|)
                weight.zero_()
                last.bias.zero_()
        return self

    def forward(self, x: Tensor, latent: Tensor | None = None) -> Tensor:
        """x Float[Tensor, "... 3"] unit frame -> Float[Tensor, "..."]."""
        if self.start is None:
            return super().forward(x, latent)
        last = self.layers[-1]
        if not self.training and not (last.weight.any() or last.bias.any()):  # adds nothing: the start alone
            return self.start(x)
        return self.start(x) + self.start.voxel * super().forward(x, latent)
