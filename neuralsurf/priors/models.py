"""The two learned priors, sized for a collection, and a trained prior read back from its checkpoint.

- `deepsdf(n_shapes, ...)`, `occupancy_network(n_shapes, ...)`: the models train.py's prior
  experiments build (one latent code per training shape for DeepSDF; the encoder gives OccNet its codes).
- `load_prior(path)`: the trained model of a run's checkpoint, rebuilt from the allowlist of
  `neuralsurf.models.spec` (weights_only; nothing in the file chooses code to run).
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import nn

from neuralsurf.checkpoints import read_model
from neuralsurf.errors import CheckpointError
from neuralsurf.models import SDFMLP, AutoDecoder, CBNDecoder, LatentCodes, OccupancyNetwork, PointNetEncoder
from neuralsurf.models.spec import REBUILDABLE


def deepsdf(n_shapes: int, latent_dim: int = 64, width: int = 256, depth: int = 8, skip_layers=(4,),
            weight_norm: bool = True, activation: str = "relu", init_radius: float = 0.25,
            code_std: float = 0.01) -> AutoDecoder:
    """A DeepSDF auto-decoder for `n_shapes` training shapes: an SDFMLP decoder taking codes of
    `latent_dim` entries (DeepSDF: 8 x 512, skip at layer 4, weight norm) and one code per shape,
    initialised N(0, code_std^2)."""
    decoder = SDFMLP(width=width, depth=depth, skip_layers=tuple(skip_layers), weight_norm=weight_norm,
                     activation=activation, latent_dim=latent_dim, init_radius=init_radius)
    return AutoDecoder(decoder, LatentCodes(n_shapes, latent_dim, init_std=code_std))


def occupancy_network(n_shapes: int, latent_dim: int = 128, encoder_hidden: int = 128, hidden: int = 256,
                      blocks: int = 5, threshold: float = 0.2, plane_dim: int = 0,
                      plane_resolution: int = 32) -> OccupancyNetwork:
    """An Occupancy Network (PointNet encoder with ResNet blocks, CBN decoder), codes of `latent_dim`
    entries, its field's zero level at occupancy probability `threshold` (the paper's 0.2); with
    `plane_dim > 0` also feature planes of that many channels (`plane_resolution`^2 cells, ConvONet).
    `n_shapes` is unused: the encoder computes each shape's code (the argument keeps one signature
    for both priors)."""
    planes = {"plane_dim": plane_dim, "plane_resolution": plane_resolution}
    return OccupancyNetwork(PointNetEncoder(latent_dim, encoder_hidden, **planes),
                            CBNDecoder(latent_dim, hidden, blocks, **planes), threshold=threshold)


def load_prior(path: str | Path, device: str | torch.device = "cpu") -> nn.Module:
    """The trained prior (an AutoDecoder or OccupancyNetwork, unit frame, eval mode) of a run's
    `checkpoints/last.pt`. Rebuilt from the allowlist of model classes (`models.spec`)."""
    stored = read_model(path, f"prior checkpoint {path} not found; pass the checkpoints/last.pt of a train.py "
                              f"experiment=shapes_* run")
    if not isinstance(stored.state.get("model_spec"), dict) or "model" not in stored.state:
        raise CheckpointError(f"{path} holds no rebuildable model; it was not written by a neuralsurf fit")
    name = stored.class_name
    if name in REBUILDABLE and not issubclass(REBUILDABLE[name], (AutoDecoder, OccupancyNetwork)):
        raise CheckpointError(f"{path} holds a {name}, not a learned prior (AutoDecoder or OccupancyNetwork): a "
                              f"single-shape field; load it with neuralsurf.load_field")
    return stored.build().to(device).eval()
