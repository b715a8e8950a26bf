"""Finds suites by name: built-in providers plus the `dvla_harness.adapters` entry points.

A provider owns a name prefix (e.g. "metaworld/") and answers two questions without
importing its simulator: which suites it has, and how to load one by name.
"""

from __future__ import annotations

import dataclasses
import importlib

# The suite contract's SuiteProvider and errors (adapters/base.py), which plugins and the
# CLI import from here (docs/plugins.md).
from adapters.base import MissingExtraError as MissingExtraError
from adapters.base import Suite, SuiteInfo, SuiteProvider, UnknownSuiteError
from adapters.base import SuiteDataError as SuiteDataError
from harness.plugins import HARNESS, load_plugins, origin, warn

ENTRY_POINT_GROUP = "dvla_harness.adapters"
# The built-in providers, by module (each has a PROVIDER): imported when suites are asked
# for, the way a plugin's entry point is, so no adapter needs to import the registry.
BUILTIN = ("adapters.metaworld", "adapters.libero", "adapters.chains", "adapters.simpler")


def _builtin_providers() -> list[SuiteProvider]:
    return [importlib.import_module(module).PROVIDER for module in BUILTIN]


# Who provided each suite prefix, as of the last providers(): "dvla-harness" or a plugin's
# "<distribution> <version>"; recorded in every run's manifest.
PROVIDED_BY: dict[str, str] = {}
# A plugin prefix's entry point ("'line' in dvla_harness.adapters"), for its errors.
ENTRY_POINTS: dict[str, str] = {}


def providers() -> list[SuiteProvider]:
    """Built-in providers, then plugins'. A plugin whose prefix overlaps one already
    registered (`metaworld/`, or another plugin's) is refused with a warning naming both,
    never allowed to shadow it."""
    found = _builtin_providers()
    by = dict.fromkeys((p.prefix for p in found), HARNESS)
    ENTRY_POINTS.clear()
    for plugin in load_plugins(ENTRY_POINT_GROUP, SuiteProvider):
        prefix = plugin.obj.prefix
        clash = next((p for p in by if prefix.startswith(p) or p.startswith(prefix)), None)
        if clash is not None:
            warn(
                f"plugin {plugin.provider} registers suites under {prefix!r}, which overlaps "
                f"{clash!r} from {by[clash]}; the plugin's are ignored (choose another prefix)"
            )
            continue
        found.append(plugin.obj)
        by[prefix] = plugin.provider
        ENTRY_POINTS[prefix] = plugin.entry_point
    PROVIDED_BY.clear()
    PROVIDED_BY.update(by)
    return found


def provider_for(name: str) -> str:
    """Who provides the suite `name` ("dvla-harness" or a plugin), for manifests and errors."""
    return next((who for prefix, who in PROVIDED_BY.items() if name.startswith(prefix)), HARNESS)


def origin_for(name: str) -> str:
    """Who provides the suite `name`, with a plugin's entry point, for its errors."""
    prefix = next((p for p in PROVIDED_BY if name.startswith(p)), "")
    return origin(PROVIDED_BY.get(prefix, HARNESS), ENTRY_POINTS.get(prefix, ""))


def list_suites() -> list[SuiteInfo]:
    out = []
    for p in providers():
        package = PROVIDED_BY.get(p.prefix, HARNESS).split(" ")[0]  # "<dist> <version>" -> dist
        out += [dataclasses.replace(info, package=package) for info in p.list_suites()]
    return out


def load_suite(name: str, split: str = "eval") -> Suite:
    """Load a suite by its full name, e.g. `metaworld/mt10` or `metaworld/mt1/reach-v3`."""
    for provider in providers():
        if name.startswith(provider.prefix):
            return provider.load_suite(name, split)
    valid = ", ".join(info.name for info in list_suites())
    raise UnknownSuiteError(f"unknown suite {name!r}; valid suites: {valid}")
