"""The `dvla-harness` command line (also `python -m harness`).

Every subcommand is a module of harness/commands/ (run, list, show, collect, train,
leaderboard, report, gate, sweep, plot); this file only assembles them and turns
`UsageError` into one line and exit status 2.

Exit statuses are defined once, in harness/errors.py (EXIT_STATUS_HELP): 0 success;
1 some episodes raised (recorded with a failure_reason), or a gate found a regression;
2 bad input (nothing written); 3 harness or I/O error (a full disk; rows kept);
130 interrupted (what finished is kept; use --resume).
"""

from __future__ import annotations

import argparse
import sys
import traceback
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from harness.console import console, err_console
from harness.errors import (
    EXIT_HARNESS,
    EXIT_INTERRUPTED,
    EXIT_STATUS_HELP,
    EXIT_USAGE,
    OWN_PACKAGES,
    HarnessError,
    InterruptedWhileSaving,
    UsageError,
    vanished_module,
)

__all__ = ["build_parser", "console", "entry", "err_console", "main"]

PACKAGE_ROOT = Path(__file__).resolve().parent.parent


def _ours(filename: str) -> bool:
    path = Path(filename).resolve()
    return path.is_relative_to(PACKAGE_ROOT) and path.relative_to(PACKAGE_ROOT).parts[0] in OWN_PACKAGES


EXAMPLES = """\
examples:
  dvla-harness run                                   # the main job (embedded default config)
  dvla-harness run --suite metaworld/mt10 --policy scripted --episodes-per-task 10 --out runs/demo
  dvla-harness run --out runs/demo --resume          # finish an interrupted run
  dvla-harness list suites | policies | tasks metaworld/mt10
  dvla-harness show runs/demo
  dvla-harness collect --suite metaworld/mt10 --policy scripted --episodes-per-task 50 --out demos/mt10
  dvla-harness train --demos demos/mt10 --recipe bidirectional --out ckpt/teacher.safetensors
  dvla-harness leaderboard runs/a runs/b             # also: report paper-table | html
  dvla-harness bench runs/ci --observations results/baselines/metaworld-mt10-smoke   # replay timing
  dvla-harness gate --baseline results/baselines/metaworld-mt10-smoke --candidate runs/ci
  dvla-harness sweep --suite metaworld/mt10 --policy fast_dvla --grid block_size=4,8,16 --out runs/sweep
  dvla-harness plot ablation runs/sweep --x block_size --y success,tokens_per_s --out fig.png
"""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="dvla-harness",
        description=(
            "Benchmark and evaluation harness for robot policies that decode discrete action "
            "tokens: success, NFE, control Hz and tokens/s per episode, into Parquet."
        ),
        epilog=EXAMPLES + "\n" + EXIT_STATUS_HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    from harness import __version__
    from harness.commands import register_all

    parser.add_argument("--version", action="version", version=f"dvla-harness {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    register_all(sub)
    return parser


def _arguments(parser: argparse.ArgumentParser, args: argparse.Namespace) -> dict[str, str]:
    """The chosen command's arguments, dest -> how the user names them (`--suite`,
    `RUN_DIR`), through its subcommand's parser (`report html`'s)."""
    names: dict[str, str] = {}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            chosen = action.choices.get(getattr(args, action.dest, None) or "")
            if chosen is not None:
                names |= _arguments(chosen, args)
        elif action.option_strings:
            names.setdefault(action.dest, max(action.option_strings, key=len))
        else:
            names.setdefault(action.dest, str(action.metavar or action.dest).upper())
    return names


def empty_argument(parser: argparse.ArgumentParser, args: argparse.Namespace) -> str:
    """The first argument given as an empty (or blank) string, by name; ''. Every value
    is a name, path or list: empty, it would silently stand for the default (`--suite ""`
    ran the default suite)."""
    names = _arguments(parser, args)
    for dest, value in vars(args).items():
        values = value if isinstance(value, list) else [value]
        if any(isinstance(v, str) and not v.strip() for v in values):
            return names.get(dest, dest)
    return ""


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    empty = empty_argument(parser, args)
    if empty:
        print(f"dvla-harness {args.command}: error: {empty} is empty; give it a value", file=sys.stderr)
        return EXIT_USAGE
    default_show = warnings.showwarning

    def show(message, category, filename, lineno, file=None, line=None):  # type: ignore[no-untyped-def]
        """The harness's own warnings (a checkpoint's dtype converted on load) as one line;
        a library's keep Python's form, with the line of code that raised them."""
        if _ours(filename) and issubclass(category, UserWarning):
            print(f"dvla-harness {args.command}: warning: {message}", file=sys.stderr)
        else:
            default_show(message, category, filename, lineno, file, line)

    warnings.showwarning = show
    try:
        return args.func(args)
    except UsageError as exc:
        print(f"dvla-harness {args.command}: error: {exc}", file=sys.stderr)  # one unwrapped line
        return EXIT_USAGE
    except HarnessError as exc:
        print(f"dvla-harness {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_HARNESS
    except InterruptedWhileSaving as exc:
        print(f"dvla-harness {args.command}: {exc}", file=sys.stderr)
        return EXIT_INTERRUPTED
    except ModuleNotFoundError as exc:
        cause = vanished_module(exc.name)
        if cause is None:
            raise  # another package's: a traceback, as any unforeseen error
        print(f"dvla-harness {args.command}: error: {cause}; then run the command again", file=sys.stderr)
        return EXIT_HARNESS
    finally:
        warnings.showwarning = default_show


def entry() -> Any:
    try:
        code = main()
    except Exception:  # a bug or an unforeseen I/O failure: the traceback, then exit 3
        traceback.print_exc()
        print("dvla-harness: internal error (traceback above); exit status 3", file=sys.stderr)
        code = EXIT_HARNESS
    sys.exit(code)
