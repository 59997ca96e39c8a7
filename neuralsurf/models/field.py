"""A model seen from the world frame: the `field` that extraction and rendering consume."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from neuralsurf.structures import Normalization


class NormalizedField(nn.Module):
    """world x[..., 3] -> signed distance in world units [...], negative inside.

    Wraps a unit-frame model: f_world(x) = scale * model(normalization.to_unit(x), latent).
    `bounds` is the world box the model was trained on (the unit cube plus `margin`).
    """

    def __init__(self, model: nn.Module, normalization: Normalization, latent: Tensor | None = None,
                 margin: float = 0.05):
        super().__init__()
        self.model = model
        self.normalization = normalization
        self.latent = latent
        self.margin = float(margin)
        half = 0.5 + margin
        corners = torch.tensor([[-half] * 3, [half] * 3], dtype=torch.float64)
        self.register_buffer("bounds", normalization.to_world(corners), persistent=False)

    def forward(self, x: Tensor) -> Tensor:
        unit = self.normalization.to_unit(x).to(torch.float32)
        latent = None if self.latent is None else self.latent.to(unit.device)
        return self.model(unit, latent) * self.normalization.scale
