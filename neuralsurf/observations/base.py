"""The observation contract: everything a fit learns from.

An `Observation` holds data in the user's world frame and the weights of its loss terms. `fit`
asks every observation for its world `bounds`, builds one `Normalization` from their union, and
calls `prepare` once: the observation returns a `Sampler` that holds its pools in the unit frame,
on the fit's device. Each step the sampler draws a typed batch (a frozen dataclass of tensors) with
the fit's `torch.Generator` and returns named, unweighted loss terms of the model on it; `fit` sums
`weights[name] * term` over all observations.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Mapping
from typing import Any

import torch
from torch import Tensor, nn

from neuralsurf.errors import ConfigError, InputError
from neuralsurf.models.grid import VoxelSDF
from neuralsurf.structures import Normalization


class NotObserved(InputError):
    """A scene lacks the data an observation needs (e.g. depth rays of a point cloud)."""


def check_weights(weights: Mapping[str, float], known: tuple[str, ...], owner: str) -> dict[str, float]:
    """The term weights of an observation as a plain dict, in the order of `known`; unknown names,
    negative weights or all zero are ConfigErrors."""
    weights = dict(weights)
    unknown = sorted(set(weights) - set(known))
    if unknown:
        raise ConfigError(f"{owner} has no loss term(s) {unknown}; its terms are {list(known)}")
    bad = {name: value for name, value in weights.items() if not (isinstance(value, (int, float)) and value >= 0)}
    if bad:
        raise ConfigError(f"{owner} term weights must be numbers >= 0, got {bad}")
    if not any(weights.values()):
        raise ConfigError(f"every loss term of {owner} is switched off; give at least one positive weight")
    return {name: float(weights[name]) for name in known if name in weights}


class Sampler(ABC):
    """An observation prepared for one fit: pools in the unit frame, on the fit's device."""

    weights: dict[str, float]
    """Weight of each loss term by name (0 or absent: the term is not computed)."""

    @abstractmethod
    def sample(self, generator: torch.Generator) -> Any:
        """One batch (a frozen dataclass of tensors), drawn with `generator` (on the CPU)."""

    @abstractmethod
    def losses(self, model: nn.Module, batch: Any) -> dict[str, Tensor]:
        """Unweighted scalar loss terms of the unit-frame `model` on `batch`, by name."""

    def start_field(self, resolution: int, box: float) -> VoxelSDF | None:
        """A closed-form field of the data over [-box, box]^3 at `resolution` cells per side at most, for a model to refine
        (`models.RefinedSDF`); None where the observation offers none."""
        return None

    def held_out_error(self, model: nn.Module) -> float | None:
        """The unit-frame `model`'s error on data kept out of the batches (what `fit` stops on), or None."""
        return None


class Observation(ABC):
    """Supervision in the world frame: data plus the weights of its loss terms."""

    name: str = "observation"
    """Prefix of its terms in logs (e.g. "points/surface")."""

    @abstractmethod
    def bounds(self) -> Tensor:
        """Float64[Tensor, "2 3"]: the world box (min, max corners) of the data."""

    @abstractmethod
    def prepare(self, normalization: Normalization, box: float, device: torch.device, seed: int) -> Sampler:
        """Build the sample pools in the unit frame of `normalization`, where the fit covers
        [-box, box]^3, on `device`; `seed` fixes every random choice made here."""


def union_bounds(observations: list[Observation]) -> Tensor:
    """Float64[Tensor, "2 3"]: the box holding every observation's bounds."""
    boxes = torch.stack([torch.as_tensor(o.bounds(), dtype=torch.float64).cpu() for o in observations])
    return torch.stack([boxes[:, 0].min(0).values, boxes[:, 1].max(0).values])
