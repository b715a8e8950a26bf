"""Loads third-party registrations from Python entry points, checking what they name."""

from __future__ import annotations

from importlib.metadata import entry_points
from typing import TypeVar

T = TypeVar("T")


def load_plugins(group: str, kind: type[T]) -> list[T]:
    """Every object named by an entry point of `group`; each must be a `kind`."""
    found: list[T] = []
    for ep in entry_points(group=group):
        obj = ep.load()
        if not isinstance(obj, kind):
            raise TypeError(
                f"entry point {ep.name!r} in {group} must be a {kind.__name__}, got {type(obj).__name__}"
            )
        found.append(obj)
    return found
