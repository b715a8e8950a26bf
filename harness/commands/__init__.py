"""Subcommands that build on run folders (leaderboard, report, gate, sweep, plot...).

One module per subcommand, found by listing this package, so adding a command never
edits a shared file. Each module defines `register(sub)`, which adds its parser to the
`argparse` subparsers and sets `func` to a callable taking the parsed arguments and
returning the exit status; raise `harness.errors.UsageError` for bad input (exit 2).
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil


def register_all(sub: argparse._SubParsersAction) -> None:
    for info in sorted(pkgutil.iter_modules(__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue
        module = importlib.import_module(f"{__name__}.{info.name}")
        module.register(sub)
