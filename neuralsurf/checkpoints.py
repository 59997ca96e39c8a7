"""Checkpoints: the file format of a fit and its one reader.

A checkpoint is a dict of tensors and plain containers, written atomically (`save_checkpoint`) and read
with `torch.load(weights_only=True)` (`load_checkpoint`). `field_state` is what a field needs (the model
as plain data, its weights, the unit frame, the box margin); `read_model` reads a model checkpoint as a
`StoredModel` record, whose `build` rebuilds the model from an allowlist (nothing in the file can choose
code to run). Each loader checks the class it needs: `load_field` a single-shape field,
`neuralsurf.priors.load_prior` a learned prior.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import nn

from neuralsurf.devices import resolve_device
from neuralsurf.errors import CheckpointError
from neuralsurf.models.field import NormalizedField
from neuralsurf.models.spec import REBUILDABLE, build_checked, check_tensors, check_weights, model_spec
from neuralsurf.structures import Normalization

__all__ = [
    "CHECKPOINT_NAME",
    "MAX_MARGIN",
    "PRIOR_CLASSES",
    "StoredModel",
    "field_state",
    "load_checkpoint",
    "load_field",
    "read_model",
    "save_checkpoint",
    "stored_class",
    "stored_margin",
]

CHECKPOINT_NAME = "last.pt"


def save_checkpoint(path: Path, state: dict[str, Any]) -> None:
    """Write `state` atomically: a temporary file in the same folder, then a rename."""
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(path.name + ".tmp")
    torch.save(state, temporary)
    os.replace(temporary, path)


def load_checkpoint(path: Path) -> dict[str, Any]:
    """Read a checkpoint written by `save_checkpoint` (tensors and plain containers only)."""
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # noqa: BLE001 - a truncated or foreign file, whatever torch raises
        raise CheckpointError(f"cannot read checkpoint {path}: {error}; delete it to start afresh") from None
    if not isinstance(state, dict):
        raise CheckpointError(f"{path} holds a {type(state).__name__}, not a neuralsurf checkpoint (a dict of "
                              f"'model', 'model_spec', ...); pass the last.pt of a run or a file of FitResult.save")
    check_tensors(state, str(path))
    return state


PRIOR_CLASSES = ("AutoDecoder", "OccupancyNetwork")
"""Model classes of learned priors (`neuralsurf.priors.load_prior`), not single-shape fields."""


def stored_class(state: dict[str, Any]) -> str | None:
    """The model class name a checkpoint's spec names (None when it has no spec)."""
    spec = state.get("model_spec")
    return spec.get("class") if isinstance(spec, dict) and isinstance(spec.get("class"), str) else None


MAX_MARGIN = 10.0
"""The largest box margin a checkpoint may carry (unit-cube widths on each side of the data)."""


def stored_margin(state: dict[str, Any], path: Path) -> float:
    """A checkpoint's box margin: a number in 0..MAX_MARGIN, else a CheckpointError naming `path`."""
    margin = state["margin"]
    if isinstance(margin, bool) or not isinstance(margin, (int, float)) or not 0 <= margin <= MAX_MARGIN:
        raise CheckpointError(f"{path}: margin is {margin!r:.60}, not a number in 0..{MAX_MARGIN:g} (unit-cube "
                              f"widths around the data); the checkpoint was tampered with or is damaged")
    return float(margin)


def field_state(model: nn.Module, normalization: Normalization, margin: float, steps: int) -> dict[str, Any]:
    """What `load_field` needs: the model as plain data, its weights, the unit frame and the box margin."""
    spec = model_spec(model) if REBUILDABLE.get(type(model).__name__) is type(model) else None
    return {"model_spec": spec, "model": model.state_dict(),
            "normalization": normalization.state_dict(), "margin": float(margin), "step": int(steps)}


@dataclass(frozen=True)
class StoredModel:
    """A model checkpoint as `read_model` found it: its file, its state and the model class its spec
    names (None when it has no spec). Each loader checks the class it needs, then calls `build`."""

    path: Path
    state: dict[str, Any]
    class_name: str | None

    def build(self, model: nn.Module | None = None) -> nn.Module:
        """The model rebuilt from its stored constructor arguments (an allowlist of neuralsurf's model
        classes and plain values: nothing in the file can choose code to run), or the stored weights
        loaded into `model`. CheckpointError when the weights do not fit."""
        if model is None:
            return build_checked(self.state["model_spec"], self.state["model"], f"{self.path}: model")
        try:
            model.load_state_dict(check_weights(self.state["model"], f"{self.path}: model"))
        except (RuntimeError, KeyError, TypeError, ValueError) as error:
            raise CheckpointError(f"{self.path} does not match its model: {error}") from None
        return model


def read_model(path: str | Path, missing: str) -> StoredModel:
    """The one reader of model checkpoints: the file at `path` read weights-only (`load_checkpoint`) as a
    `StoredModel`. CheckpointError for a missing file (`missing` says what to pass instead) or a file that
    is not a neuralsurf checkpoint."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(missing)
    state = load_checkpoint(path)
    return StoredModel(path, state, stored_class(state))


def load_field(path: str | Path, model: nn.Module | None = None, device: str | torch.device = "cpu") -> NormalizedField:
    """The world-frame field saved by `FitResult.save` or by a fit's checkpoint (`run/checkpoints/last.pt`):
    its model rebuilt from the checkpoint (`read_model`; or pass `model` to load the weights into one of your own).
    Raises CheckpointError for a file that is not such a checkpoint."""
    stored = read_model(path, f"checkpoint {path} not found; pass the last.pt of a run or a file of FitResult.save")
    state, name = stored.state, stored.class_name
    missing = [key for key in ("model", "normalization", "margin") + (("model_spec",) if model is None else ())
               if key not in state]
    if missing:
        raise CheckpointError(f"{path} lacks {missing}: it was not written by neuralsurf's fit or FitResult.save "
                              f"(checkpoints of neuralsurf before 0.2 cannot be loaded; fit again)")
    if model is None and state["model_spec"] is None:
        raise CheckpointError(f"{path} holds a model of a class neuralsurf cannot rebuild; pass it: "
                              f"load_field(path, model=YourModel(...))")
    if name in PRIOR_CLASSES:
        raise CheckpointError(f"{path} holds a learned prior ({name}), not a single-shape field; "
                              f"load it with neuralsurf.priors.load_prior and complete a shape with complete_cloud")
    model = stored.build(model)
    margin = stored_margin(state, Path(path))
    try:
        normalization = Normalization.from_state_dict(state["normalization"])
    except (RuntimeError, KeyError, TypeError, ValueError, AttributeError) as error:
        raise CheckpointError(f"{path}: its normalization is not readable: {error}") from None
    if not bool(torch.isfinite(normalization.center).all()):
        raise CheckpointError(f"{path}: its normalization centre is {normalization.center.tolist()}, not finite; the "
                              f"checkpoint was tampered with or is damaged")
    return NormalizedField(model, normalization, margin=margin).to(resolve_device(device)).eval()
