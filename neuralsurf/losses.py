"""Loss terms for fitting signed distance fields: pure functions returning scalar tensors.

Observations (neuralsurf.observations) evaluate them on their batches; `fit` weights and sums them.
"""

from __future__ import annotations

import torch
from torch import Tensor


def clamped_l1(pred: Tensor, target: Tensor, clamp: float) -> Tensor:
    """DeepSDF's loss: mean |clamp(pred, -d, d) - clamp(target, -d, d)|. pred, target: [n]."""
    return (pred.clamp(-clamp, clamp) - target.clamp(-clamp, clamp)).abs().mean()


def surface_loss(sdf_on_surface: Tensor) -> Tensor:
    """Mean |f| on surface samples: the zero level set passes through the data. [n] -> []."""
    return sdf_on_surface.abs().mean()


def normal_loss(gradient: Tensor, normals: Tensor) -> Tensor:
    """Mean 1 - cos(grad f, n) on surface samples. gradient, normals: [n, 3] -> []."""
    return (1 - torch.nn.functional.cosine_similarity(gradient, normals, dim=-1)).mean()


def eikonal_loss(gradient: Tensor) -> Tensor:
    """Mean (|grad f| - 1)^2 (IGR): f is a distance. gradient: [n, 3] -> []."""
    return ((gradient.norm(dim=-1) - 1) ** 2).mean()


def off_surface_loss(sdf_off_surface: Tensor, alpha: float = 100.0) -> Tensor:
    """Mean exp(-alpha |f|) (SIREN): no zero level set away from the data. [n] -> []."""
    return torch.exp(-alpha * sdf_off_surface.abs()).mean()
