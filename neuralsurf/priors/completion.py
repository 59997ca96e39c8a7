"""Shape completion with a learned prior.

- DeepSDF: `reconstruct_latent(decoder, observations)` optimises one latent code under the frozen
  decoder (`fit(LatentConditioned(decoder, dim), [*observations, LatentPrior()], trainable=[code])`)
  from any observation in the prior's unit frame: SDF samples, a (partial) cloud as `PointSamples`,
  or depth views as `DepthRays`.
- Occupancy Network: `OccupancyNetwork.field_from_cloud(points)`, one forward pass of the encoder.

The prior's frame is the collection's unit frame: observations must be posed in it (DeepSDF and
OccNet assume the canonical pose of their training shapes).
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

from torch import nn

from neuralsurf.errors import ConfigError
from neuralsurf.models.latent import LatentConditioned
from neuralsurf.observations.base import Observation
from neuralsurf.observations.collection import LatentPrior
from neuralsurf.structures import Normalization
from neuralsurf.training import FitResult, default_optimizer, fit


def reconstruct_latent(decoder: nn.Module, observations: Sequence[Observation], *, steps: int = 400,
                       lr: float = 5e-3, prior_weight: float = 1e-4, init_std: float = 0.0, seed: int = 0,
                       device: str = "cpu", progress: bool = False, **fit_options) -> FitResult:
    """DeepSDF's reconstruction: the code of a LatentConditioned(decoder) fitted to `observations`
    (prior unit frame) plus the code prior `prior_weight * ||z||^2`, with the decoder frozen.
    Returns the FitResult; its `field` is the completed shape, `model.code` the code."""
    latent_dim = getattr(decoder, "latent_dim", 0)
    if not latent_dim:
        raise ConfigError(f"reconstruct_latent needs a decoder with latent codes (latent_dim > 0), got "
                          f"{type(decoder).__name__} with latent_dim={latent_dim}")
    model = LatentConditioned(decoder, latent_dim, init_std=init_std)
    prior = [LatentPrior({"code": prior_weight})] if prior_weight > 0 else []
    return fit(model, [*observations, *prior], steps=steps, trainable=[model.code], encoding_lr=None,
               optimizer=functools.partial(default_optimizer, lr=lr), normalization=Normalization(), seed=seed,
               device=device, progress=progress, **fit_options)
