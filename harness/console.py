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
from rich.measure import Measurement
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

console = Console(width=None if sys.stdout.isatty() else 160)
err_console = Console(stderr=True, width=None if sys.stderr.isatty() else 140)


def print_table(table: Any, target: Console | None = None) -> None:
    """Print a rich Table whole. In a terminal its columns fold to the window (no name
    is cut to `fast_…`); written to a pipe or a file, the console widens to the table's
    natural width, so `dvla-harness leaderboard RUN > file` keeps every name and count
    on one line."""
    target = target or console
    if target.is_terminal:
        target.print(table)
        return
    need = Measurement.get(target, target.options.update_width(100_000), table).maximum
    width = target.width
    target.width = max(width, need)
    try:
        target.print(table)
    finally:
        target.width = width


def episode_progress(
    quiet: bool,
) -> tuple[AbstractContextManager[None], Callable[[int, int], Callable[[bool], None]]]:
    """A display to wrap the work in, and `start(total, skipped)`, which shows the bar and
    returns the per-episode tick.

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
        if skipped:
            err_console.print(f"resuming: {skipped} episode(s) already recorded, {total} to run")
        progress.start()
        state["shown"] = True
        task_id = progress.add_task("episodes", total=total, success="success -")

        started = time.monotonic()
        step = max(1, math.ceil(total / 20))  # a plain line every 5% when not on a terminal

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
