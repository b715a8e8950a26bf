"""The subcommands of `dvla-harness`, one module each.

One module per subcommand, found by listing this package, so adding a command never
edits a shared file. Each module defines `register(sub)`, which adds its parser to the
`argparse` subparsers and sets `func` to a callable taking the parsed arguments and
returning the exit status; raise `harness.errors.UsageError` for bad input (exit 2).
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil

# The evaluation loop's commands first in --help, then the rest alphabetically.
FIRST = ("run", "listing", "show", "collect", "train")


def register_all(sub: argparse._SubParsersAction) -> None:
    names = [m.name for m in pkgutil.iter_modules(__path__) if not m.name.startswith("_")]
    for name in sorted(names, key=lambda n: (FIRST.index(n) if n in FIRST else len(FIRST), n)):
        importlib.import_module(f"{__name__}.{name}").register(sub)
