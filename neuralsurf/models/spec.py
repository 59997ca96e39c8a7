"""Models as plain data: the constructor arguments a model was built with, and the rebuild from them.

A checkpoint stores `model_spec(model)`, e.g. {"class": "SDFMLP", "arguments": {"width": 64, ...,
"encoding": {"class": "HashGrid", "arguments": {...}}}}. `build_model` rebuilds it from an allowlist
(the classes marked `@rebuildable` in neuralsurf) and plain values only, so nothing read from a file
can name a function to call: a crafted spec is an error, never code run.
"""

from __future__ import annotations

import functools
import inspect
import threading
from typing import Any

import torch
from torch import Tensor, nn
from torch.nn.modules import module as torch_module

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
    try:
        return cls(**arguments)
    except (TypeError, ValueError, OverflowError, ZeroDivisionError, RuntimeError) as error:
        raise CheckpointError(f"{where}: {cls.__name__} cannot be built from the stored arguments ({error}); "
                              f"the checkpoint was tampered with or written by another version") from None


def check_storage(value: Tensor, where: str) -> None:
    """A CheckpointError naming `where` unless the tensor `value` (read from a file) is a dense,
    contiguous tensor whose storage holds all its values: an expanded view (stride 0) or any tensor
    larger than the bytes stored for it could make a reader allocate far more than the file holds."""
    if value.layout != torch.strided or value.is_quantized:
        raise CheckpointError(f"{where} is a {value.layout} tensor, not a dense one; the checkpoint was not written "
                              f"by neuralsurf or was tampered with")
    needed = (value.storage_offset() + value.numel()) * value.element_size()
    stored = value.untyped_storage().nbytes()
    if not value.is_contiguous() or stored < needed:
        raise CheckpointError(f"{where}: a tensor of shape {tuple(value.shape)} whose file stores {stored} bytes for "
                              f"its {needed} (an expanded or non-contiguous view); the checkpoint was tampered with")


def check_tensors(state: Any, where: str) -> None:
    """`check_storage` on every tensor in `state` (nested dicts, lists and tuples, as read from a file)."""
    stack = [(state, where)]
    while stack:
        value, name = stack.pop()
        if isinstance(value, Tensor):
            check_storage(value, name)
        elif isinstance(value, dict):
            stack += [(item, f"{name}[{key!r:.60}]") for key, item in value.items()]
        elif isinstance(value, (list, tuple)):
            stack += [(item, f"{name}[{index}]") for index, item in enumerate(value)]


def stored_elements(weights: dict[str, Tensor]) -> int:
    """The values `weights` (checked by `check_storage`) can hold, counted from the bytes of their distinct
    storages (a storage shared by several tensors counts once), in units of the smallest element size
    that uses it."""
    storages: dict[int, tuple[int, int]] = {}
    for value in weights.values():
        storage = value.untyped_storage()
        key = storage.data_ptr() if storage.nbytes() else id(value)
        size = min(value.element_size(), storages.get(key, (0, value.element_size()))[1])
        storages[key] = (storage.nbytes(), size)
    return sum(nbytes // size for nbytes, size in storages.values())


def check_weights(weights: Any, where: str) -> dict[str, Tensor]:
    """`weights` (a state dict read from a file) as {name: tensor}, every tensor dense with its values
    stored (`check_storage`) and every floating tensor finite; a CheckpointError naming `where` and the
    bad entry otherwise."""
    if not isinstance(weights, dict):
        raise CheckpointError(f"{where}: the weights are a {type(weights).__name__}, not a dict of tensors; "
                              f"the checkpoint was not written by neuralsurf or was tampered with")
    bad = [repr(k)[:60] for k, v in weights.items() if not (isinstance(k, str) and isinstance(v, Tensor))]
    if bad:
        raise CheckpointError(f"{where}: weight entries {bad[:5]} are not named tensors; the checkpoint was not "
                              f"written by neuralsurf or was tampered with")
    for name, value in weights.items():
        check_storage(value, f"{where}: weight {name!r}")
    for name, value in weights.items():
        if value.is_floating_point() and not bool(torch.isfinite(value).all()):
            count = int((~torch.isfinite(value)).sum())
            raise CheckpointError(f"{where}: weight {name!r} holds {count} NaN or inf of {value.numel()} values; "
                                  f"the fit diverged before it was saved or the file is damaged: fit again")
    return weights


def _integers(value: Any, where: str):
    """(where, value) of every int (not bool) in a spec's arguments, nested specs and lists included."""
    if isinstance(value, dict):
        for key, item in value.items():
            yield from _integers(item, f"{where}.{key}" if key != "arguments" else where)
    elif isinstance(value, (list, tuple)):
        for item in value:
            yield from _integers(item, where)
    elif isinstance(value, int) and not isinstance(value, bool):
        yield where, value


def _meta_skeleton(spec: Any, tensors: int, elements: int, where: str) -> nn.Module:
    """`build_model(spec)` on the meta device (no memory), stopped with a CheckpointError once it
    registers more modules or parameter values than `tensors` and `elements` (the stored weights')
    can account for."""
    limits = {"modules": 8 * tensors + 64, "values": 4 * elements + 2**20}
    counts = dict.fromkeys(limits, 0)
    thread = threading.get_ident()

    def count(kind: str, amount: int) -> None:
        if threading.get_ident() != thread:
            return
        counts[kind] += amount
        if counts[kind] > limits[kind]:
            raise CheckpointError(f"{where}: the stored arguments describe a model larger than its stored weights "
                                  f"({tensors} tensors, {elements} values); the checkpoint was tampered with")

    hooks = [
        torch_module.register_module_module_registration_hook(lambda m, n, sub: count("modules", 1)),
        torch_module.register_module_parameter_registration_hook(
            lambda m, n, p: count("values", 0 if p is None else p.numel())),
        torch_module.register_module_buffer_registration_hook(
            lambda m, n, b: count("values", 0 if b is None else b.numel())),
    ]
    try:
        with torch.device("meta"):
            return build_model(spec, where)
    finally:
        for hook in hooks:
            hook.remove()


def build_checked(spec: Any, weights: Any, where: str = "model") -> nn.Module:
    """The model of `spec` (`model_spec`'s output) holding `weights` (its state dict, read from a file).

    Nothing is allocated before the spec is known to agree with the weights: every integer argument
    must stay within the stored values' count (from the bytes the file stores, `stored_elements`), the model is first built on the meta device (its
    construction stopped if it outgrows the stored weights), and its state dict's names and shapes
    must equal the stored ones. Raises CheckpointError, naming `where`, otherwise.
    """
    weights = check_weights(weights, where)
    elements = stored_elements(weights)
    for name, value in _integers(spec, where):
        if abs(value) > max(elements, 64):
            raise CheckpointError(f"{name}={value} exceeds the {elements} values the checkpoint stores: its "
                                  f"model arguments disagree with its weights (tampered with or damaged)")
    skeleton = _meta_skeleton(spec, len(weights), elements, where).state_dict()
    missing, unexpected = sorted(set(skeleton) - set(weights)), sorted(set(weights) - set(skeleton))
    shapes = [f"{k} {tuple(weights[k].shape)} != {tuple(v.shape)}" for k, v in skeleton.items()
              if k in weights and weights[k].shape != v.shape]
    if missing or unexpected or shapes:
        raise CheckpointError(f"{where}: the stored arguments and weights disagree (missing {missing[:5]}, "
                              f"unexpected {unexpected[:5]}, shapes {shapes[:5]}); the checkpoint was tampered "
                              f"with or is damaged")
    model = build_model(spec, where)
    try:
        model.load_state_dict(weights)
    except (RuntimeError, ValueError, TypeError) as error:
        raise CheckpointError(f"{where}: the weights do not load into the model: {error}") from None
    return model
