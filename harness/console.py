"""Terminal output shared by every subcommand: where tables and progress go.

Pipes and CI logs get wide tables instead of rich's 80-column default; progress goes
to stderr so that stdout stays the table (or the Markdown/CSV a command prints).
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager
from typing import Any

from rich.console import Console
from rich.markup import escape
from rich.measure import Measurement
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from rich.table import Table
from rich.text import Text

from results.table_fit import Fit, fit_table, hidden_note, legend_lines

console = Console(width=None if sys.stdout.isatty() else 160)
err_console = Console(stderr=True, width=None if sys.stderr.isatty() else 140)


def print_table(
    table: Any, target: Console | None = None, fit: Fit | None = None, wide: bool = False
) -> None:
    """Print a rich Table. In a terminal it keeps the columns that fit the window, in
    order of importance, with no name broken mid-word, and says beneath it what it left
    out (results/table_fit.py); with `wide` (`--wide`), or written to a pipe or a file,
    the console widens to the table's natural width, so `dvla-harness leaderboard RUN >
    file` keeps every column, name and count on one line."""
    target = target or console
    if target.is_terminal and not wide:
        fitted = fit_table(table, target.width, fit)
        target.print(fitted.table)
        for line in legend_lines(fitted.legend, (fit or Fit()).key_name, target.width):
            target.print(line, markup=False, highlight=False)
        if fitted.hidden:
            note = hidden_note(fitted.hidden, (fit or Fit()).keys, "--wide shows every column")
            target.print(note, style="dim", markup=False, highlight=False)
        return
    need = Measurement.get(target, target.options.update_width(100_000), table).maximum
    width = target.width
    target.width = max(width, need)
    try:
        target.print(table)
    finally:
        target.width = width


def print_note(label: str, text: str, target: Console | None = None) -> None:
    """A warning or note line: in a terminal wrapped at words under a hanging indent (a
    300-character line is unreadable folded by the terminal); to a pipe or a file, one
    line, so that grep finds it whole. `label` is rich markup ("[yellow]warning:[/yellow]")."""
    target = target or err_console
    if not target.is_terminal:
        target.print(f"{label} {escape(text)}", highlight=False, soft_wrap=True)
        return
    grid = Table.grid(padding=(0, 1))
    grid.add_column(no_wrap=True)
    grid.add_column(overflow="fold")
    grid.add_row(label, Text(text))
    target.print(grid)


def add_wide_argument(p: Any) -> None:
    p.add_argument(
        "--wide",
        action="store_true",
        help="print every column however wide the terminal (by default a table in a terminal keeps "
        "the columns that fit and names the others beneath it; piped output is always whole)",
    )


# Off a terminal (a CI log, nohup), a plain progress line every this many episodes at
# most (every 5% when that is fewer): a 2,000-episode run is not silent for minutes.
PLAIN_LINE_EVERY = 10


def episode_progress(
    quiet: bool, folder: Any = None
) -> tuple[AbstractContextManager[None], Callable[[int, int], Callable[[bool], None]]]:
    """A display to wrap the work in, and `start(total, skipped)`, which names the run
    folder (once it is open: a refused folder's error stays the first line), shows the
    bar and returns the per-episode tick.

    The bar appears only once `start` is called: a live display stopped before it showed
    anything still ends with an empty line, which would put a blank line before an error
    raised while the run folder is being opened (an existing folder, a held lock).
    """
    progress = Progress(
        TextColumn("[bold]episodes"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.fields[success]}"),
        TimeElapsedColumn(),
        TextColumn("ETA"),
        TimeRemainingColumn(),
        console=err_console,
        # Off a terminal the plain lines below are the whole display: rich would add its
        # own last frame when it stops, a duplicate of the last plain line.
        disable=quiet or not err_console.is_terminal,
    )
    state = {"done": 0, "ok": 0, "shown": False}

    @contextmanager
    def display() -> Iterator[None]:
        try:
            yield
        finally:
            if state["shown"]:
                progress.stop()

    def start(total: int, skipped: int) -> Callable[[bool], None]:
        if folder is not None and not quiet:
            err_console.print(f"run folder: {folder}", highlight=False, soft_wrap=True)
        if skipped:
            err_console.print(f"resuming: {skipped} episode(s) already recorded, {total} to run")
        progress.start()
        state["shown"] = True
        task_id = progress.add_task("episodes", total=total, success="success -")

        started = time.monotonic()
        step = max(1, min(PLAIN_LINE_EVERY, math.ceil(total / 20)))  # plain lines off a terminal

        def tick(success: bool) -> None:
            state["done"] += 1
            state["ok"] += int(success)
            rate = 100 * state["ok"] / state["done"]
            summary = f"success {rate:.0f}% ({state['ok']}/{state['done']})"
            progress.update(task_id, advance=1, success=summary)
            done = state["done"]
            if not quiet and not err_console.is_terminal and (done % step == 0 or done == total):
                elapsed = time.monotonic() - started
                eta = elapsed / done * (total - done)
                err_console.print(
                    f"episodes {done}/{total} ({100 * done / total:.0f}%), {summary}, "
                    f"{elapsed:.0f} s elapsed, ETA {eta:.0f} s"
                )

        return tick

    return display(), start


def raise_interrupt(signum: int, frame: Any) -> None:
    raise KeyboardInterrupt
