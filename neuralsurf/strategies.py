"""Strategies chosen by name: the one registry behind every option that picks behaviour.

A family of interchangeable pieces (depth noise models, normal sources, ICP estimations, ...)
registers each piece under the name a config uses (`@register("depth noise", "kinect")`); the code
that takes the option calls `choose(family, value)`, which returns the piece for a registered name,
or `value` itself when the caller passes a piece of its own (an object, not a string). An unknown
name is a ConfigError naming the family's choices.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TypeVar

from neuralsurf.errors import ConfigError

T = TypeVar("T")

_FAMILIES: dict[str, dict[str, Any]] = {}


def register(family: str, name: str) -> Callable[[T], T]:
    """Decorator: register a strategy (function, class or object) as `name` in `family`."""
    def add(strategy: T) -> T:
        members = _FAMILIES.setdefault(family, {})
        if name in members and members[name] is not strategy:
            raise ValueError(f"{family} {name!r} is registered twice")
        members[name] = strategy
        return strategy

    return add


def names(family: str) -> tuple[str, ...]:
    """The registered names of `family`, in registration order."""
    return tuple(_FAMILIES.get(family, {}))


def choose(family: str, value: Any) -> Any:
    """The strategy `value` names in `family`; a non-string `value` is returned as it is (a
    strategy of the caller's own). ConfigError for an unknown name, listing the choices."""
    if not isinstance(value, str):
        return value
    members = _FAMILIES.get(family, {})
    if value not in members:
        raise ConfigError(f"unknown {family} {value!r}; choose one of {', '.join(map(repr, members)) or 'none'}")
    return members[value]


def name_of(family: str, strategy: Any) -> str | None:
    """The registered name of `strategy` in `family` (None for one of the caller's own)."""
    return next((name for name, member in _FAMILIES.get(family, {}).items() if member is strategy), None)
