"""Models as plain data: the constructor arguments a model was built with, and the rebuild from them.

A checkpoint stores `model_spec(model)`, e.g. {"class": "SDFMLP", "arguments": {"width": 64, ...,
"encoding": {"class": "HashGrid", "arguments": {...}}}}. `build_model` rebuilds it from an allowlist
(the classes marked `@rebuildable` in neuralsurf) and plain values only, so nothing read from a file
can name a function to call: a crafted spec is an error, never code run.
"""

from __future__ import annotations

import functools
import inspect
from typing import Any

from torch import nn

from neuralsurf.errors import CheckpointError

REBUILDABLE: dict[str, type[nn.Module]] = {}
"""Class name -> model class that `build_model` may construct."""

_PLAIN = (type(None), bool, int, float, str)


def rebuildable(cls: type[nn.Module]) -> type[nn.Module]:
    """Class decorator: each instance remembers its constructor arguments (`constructor_arguments`)
    and the class joins the allowlist of `build_model`."""
    init = cls.__init__
    signature = inspect.signature(init)

    @functools.wraps(init)
    def recording_init(self, *args, **kwargs):
        init(self, *args, **kwargs)
        bound = signature.bind(self, *args, **kwargs)
        bound.apply_defaults()
        self.__dict__["constructor_arguments"] = {k: v for k, v in bound.arguments.items() if k != "self"}

    cls.__init__ = recording_init
    REBUILDABLE[cls.__name__] = cls
    return cls


def _plain(value: Any, where: str) -> Any:
    """A constructor argument as plain data (nested modules as specs)."""
    if isinstance(value, nn.Module):
        return model_spec(value)
    if isinstance(value, (list, tuple)):
        return [_plain(item, where) for item in value]
    if isinstance(value, _PLAIN):
        return value
    raise CheckpointError(f"{where} is a {type(value).__name__}, which a checkpoint cannot store as plain data")


def model_spec(model: nn.Module) -> dict[str, Any]:
    """{"class": name, "arguments": plain constructor arguments} of a `@rebuildable` model."""
    arguments = model.__dict__.get("constructor_arguments")
    if arguments is None or REBUILDABLE.get(type(model).__name__) is not type(model):
        raise CheckpointError(
            f"{type(model).__name__} does not record its constructor arguments; decorate the class with "
            f"neuralsurf.models.rebuildable, or pass the model to load_field yourself"
        )
    name = type(model).__name__
    return {"class": name, "arguments": {k: _plain(v, f"{name}.{k}") for k, v in arguments.items()}}


def _value(value: Any, where: str) -> Any:
    if isinstance(value, dict):
        return build_model(value, where)
    if isinstance(value, list):
        return tuple(_value(item, where) for item in value)
    if isinstance(value, _PLAIN):
        return value
    raise CheckpointError(f"{where}: {type(value).__name__} is not a plain value; the checkpoint is not neuralsurf's")


def build_model(spec: Any, where: str = "model") -> nn.Module:
    """Rebuild a model from `model_spec`'s output. Only allowlisted classes and plain values pass."""
    if not (isinstance(spec, dict) and set(spec) == {"class", "arguments"} and isinstance(spec["arguments"], dict)):
        raise CheckpointError(f"{where}: a model spec is {{'class': name, 'arguments': {{...}}}}, got {spec!r:.200}")
    cls = REBUILDABLE.get(spec["class"]) if isinstance(spec["class"], str) else None
    if cls is None:
        raise CheckpointError(
            f"{where}: class {spec['class']!r:.100} is not a neuralsurf model ({', '.join(sorted(REBUILDABLE))}); "
            f"the checkpoint was not written by neuralsurf or was tampered with"
        )
    arguments = {}
    for key, value in spec["arguments"].items():
        if not isinstance(key, str) or key not in inspect.signature(cls).parameters:
            raise CheckpointError(f"{where}: {cls.__name__} takes no argument {key!r:.100}")
        arguments[key] = _value(value, f"{where}.{key}")
    return cls(**arguments)
