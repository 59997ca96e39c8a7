"""Loss terms for fitting signed distance fields: pure functions returning scalar tensors.

`sdf_losses` combines them with weights from the config into a dict whose "total" is optimised;
a term whose weight is zero, or whose data is missing (no normals), is left out.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from neuralsurf.errors import ConfigError
from neuralsurf.sampling import SDFBatch


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


@dataclass(frozen=True)
class LossWeights:
    """Weights of the SDF loss terms (0 switches a term off) and their parameters."""

    surface: float = 3.0
    """|f| on the input points."""
    sdf: float = 1.0
    """Clamped L1 to the approximate SDF of near-surface and free-space samples."""
    normal: float = 0.1
    """1 - cos between grad f and the input normals."""
    eikonal: float = 0.1
    """(|grad f| - 1)^2 on all samples."""
    off_surface: float = 0.0
    """exp(-alpha |f|) on free-space samples; useful when there are no normals."""
    clamp: float = 0.1
    """DeepSDF's clamp distance, unit frame."""
    off_surface_alpha: float = 100.0

    def __post_init__(self) -> None:
        negative = {k: v for k, v in self.__dict__.items() if v < 0}
        if negative:
            raise ConfigError(f"loss weights and parameters must be >= 0, got {negative}")


@dataclass(frozen=True)
class SDFOutputs:
    """The model evaluated on a batch (unit frame)."""

    surface: Tensor
    """Float[Tensor, "n"]: f at surface points."""
    near: Tensor
    """Float[Tensor, "m"]: f at near-surface points."""
    free: Tensor
    """Float[Tensor, "k"]: f at free-space points."""
    surface_gradient: Tensor
    """Float[Tensor, "n 3"]: grad f at surface points."""
    gradient: Tensor
    """Float[Tensor, "n+m+k 3"]: grad f at all points."""


def evaluate_sdf_batch(model, batch: SDFBatch, latent: Tensor | None = None) -> SDFOutputs:
    """One forward pass over all samples of `batch`, with gradients kept for the loss."""
    points = torch.cat([batch.surface_points, batch.near_points, batch.free_points]).requires_grad_(True)
    values = model(points, latent)
    (gradient,) = torch.autograd.grad(values.sum(), points, create_graph=True)
    n, m = len(batch.surface_points), len(batch.near_points)
    return SDFOutputs(values[:n], values[n : n + m], values[n + m :], gradient[:n], gradient)


def sdf_losses(outputs: SDFOutputs, batch: SDFBatch, weights: LossWeights) -> dict[str, Tensor]:
    """Weighted loss terms and their sum under "total" (each term unweighted under its name)."""
    terms: dict[str, Tensor] = {}
    if weights.surface:
        terms["surface"] = surface_loss(outputs.surface)
    if weights.sdf and batch.near_sdf is not None:
        pred = torch.cat([outputs.near, outputs.free])
        target = torch.cat([batch.near_sdf, batch.free_sdf])
        terms["sdf"] = clamped_l1(pred, target, weights.clamp)
    if weights.normal and batch.surface_normals is not None:
        terms["normal"] = normal_loss(outputs.surface_gradient, batch.surface_normals)
    if weights.eikonal:
        terms["eikonal"] = eikonal_loss(outputs.gradient)
    if weights.off_surface:
        terms["off_surface"] = off_surface_loss(outputs.free, weights.off_surface_alpha)
    if not terms:
        raise ConfigError("every loss term is switched off or lacks its data; give at least one positive weight")
    terms["total"] = sum(getattr(weights, name) * value for name, value in terms.items())
    return terms
