"""Finds suites by name: built-in providers plus the `dvla_harness.adapters` entry points.

A provider owns a name prefix (e.g. "metaworld/") and answers two questions without
importing its simulator: which suites it has, and how to load one by name.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from adapters.base import Suite, SuiteInfo
from harness.plugins import load_plugins

ENTRY_POINT_GROUP = "dvla_harness.adapters"


class UnknownSuiteError(LookupError):
    """The name matches no suite; the message lists the valid ones."""


class SuiteDataError(ValueError):
    """A suite's own definition files are wrong (e.g. a chain file naming an unknown
    subtask); the message names the file, the entry and the fix."""


class MissingExtraError(RuntimeError):
    """The suite's simulator is not installed; the message names the pip extra."""


@dataclass(frozen=True)
class SuiteProvider:
    prefix: str
    list_suites: Callable[[], list[SuiteInfo]]
    # load_suite(name, split): "eval" is the protocol's episodes; "train" gives episodes
    # disjoint from them where the suite can (for demonstrations), else the same ones.
    load_suite: Callable[[str, str], Suite]


def _builtin_providers() -> list[SuiteProvider]:
    from adapters import chains, libero, metaworld, simpler

    return [metaworld.PROVIDER, libero.PROVIDER, chains.PROVIDER, simpler.PROVIDER]


def _plugin_providers() -> list[SuiteProvider]:
    return load_plugins(ENTRY_POINT_GROUP, SuiteProvider)


def providers() -> list[SuiteProvider]:
    return _builtin_providers() + _plugin_providers()


def list_suites() -> list[SuiteInfo]:
    return [info for p in providers() for info in p.list_suites()]


def load_suite(name: str, split: str = "eval") -> Suite:
    """Load a suite by its full name, e.g. `metaworld/mt10` or `metaworld/mt1/reach-v3`."""
    for provider in providers():
        if name.startswith(provider.prefix):
            return provider.load_suite(name, split)
    valid = ", ".join(info.name for info in list_suites())
    raise UnknownSuiteError(f"unknown suite {name!r}; valid suites: {valid}")
