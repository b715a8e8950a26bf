"""Loads third-party registrations from Python entry points, checking what they name.

One bad package must not break the harness: an entry point that fails to import,
raises while loading, or names the wrong kind of object is skipped with a one-line
warning on stderr naming its package and the error, and everything else still lists
and runs. Each plugin object is returned with the distribution that provided it, so
registries can refuse a name the harness (or another plugin) already has, and
manifests can record who provided what.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from importlib.metadata import EntryPoint, entry_points
from pathlib import Path
from typing import Generic, TypeVar

T = TypeVar("T")
HARNESS = "dvla-harness"
# A clone of the repository: its root holds the pinned constraints next to the packages.
_CLONE = Path(__file__).resolve().parent.parent


def install_hint(extra: str, package: str = HARNESS) -> str:
    """How to install an extra, in the form that works where the user is: run from a
    clone, `pip install -c constraints.txt ".[extra]"` in it (what the README does), and
    the index form beside it; a plugin's or an installed harness's extra, the index form."""
    index = f"pip install '{package}[{extra}]'"
    if (
        package == HARNESS
        and (_CLONE / "constraints.txt").is_file()
        and (_CLONE / "pyproject.toml").is_file()
    ):
        return f'pip install -c constraints.txt ".[{extra}]" in {_CLONE} (from an index: {index})'
    return index


_warned: set[str] = set()


@dataclass(frozen=True)
class Plugin(Generic[T]):
    obj: T
    provider: str  # "<distribution> <version>", e.g. "dvla-line-plugin 0.1"
    entry_point: str = ""  # "'constant' in dvla_harness.policies": where the package names it


def origin(provider: str, entry_point: str = "") -> str:
    """Who to blame for a plugin's object, in words: its package and the entry point that
    names it (what its author looks up), e.g. "dvla-line-plugin 0.1, entry point 'constant'
    in dvla_harness.policies"."""
    return f"{provider}, entry point {entry_point}" if entry_point else provider


def one_line(exc: BaseException) -> str:
    """An exception as `Type: message` on one line (a CUDA error's text spans several)."""
    return " ".join(f"{type(exc).__name__}: {exc}".split())


def provider_of(ep: EntryPoint) -> str:
    dist = ep.dist
    return f"{dist.name} {dist.version}" if dist is not None else f"the module {ep.module}"


def warn(message: str) -> None:
    """Once per message and process, on stderr (a CLI's warnings channel)."""
    if message not in _warned:
        _warned.add(message)
        print(f"warning: {message}", file=sys.stderr)


def load_plugins(group: str, kind: type[T]) -> list[Plugin[T]]:
    """Every `kind` named by an entry point of `group`, with its provider; the rest
    skipped with a warning."""
    found: list[Plugin[T]] = []
    for ep in entry_points(group=group):
        where = f"plugin {provider_of(ep)}: entry point {ep.name!r} ({group})"
        try:
            obj = ep.load()
        except Exception as exc:
            warn(f"{where} failed to load ({type(exc).__name__}: {exc}); skipped")
            continue
        if not isinstance(obj, kind):
            warn(f"{where} must name a {kind.__name__}, got {type(obj).__name__}; skipped")
            continue
        found.append(Plugin(obj, provider_of(ep), f"{ep.name!r} in {group}"))
    return found
