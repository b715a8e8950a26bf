"""What a policy declares to be found by name: its `PolicySpec` and its parameters.

A policy's parameters are a frozen dataclass whose fields carry a help text and a valid
range (`param(...)`); policies/registry.py parses, validates and lists them from that one
declaration. Kept apart from the registry, which finds the built-in policies, so that
they declare themselves without importing it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from policies.base import Policy


def param(
    default: Any,
    help: str,
    *,
    low: float | None = None,
    high: float | None = None,
    choices: tuple[Any, ...] | None = None,
    identity: bool = True,
) -> Any:
    """A policy parameter: a dataclass field with its help text and valid range.

    `identity=False` marks a parameter that says how to reach a policy, not what it is
    (where a secret is read from): it is left out of the recorded parameters, so it never
    changes a configuration's id, and a run resumes across a rotated or moved key."""
    metadata = {"help": help, "low": low, "high": high, "choices": choices, "identity": identity}
    return field(default=default, metadata=metadata)


@dataclass(frozen=True)
class PolicySpec:
    name: str
    summary: str
    params: type  # a frozen dataclass built from `param(...)` fields
    build: Callable[[Any], Policy]
    # Suite name prefixes this policy can act in; empty means any suite.
    suites: tuple[str, ...] = ()
    extra: str = ""


@dataclass(frozen=True)
class NoParams:
    pass
