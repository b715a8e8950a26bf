"""Errors the CLI turns into one clear line, and the exit statuses every command uses."""

import re
from collections.abc import Iterable

# Exit statuses, defined once (README "Exit status", `dvla-harness run --help`).
EXIT_OK = 0  # every episode ran cleanly (failing to succeed is a result, not an error)
EXIT_EPISODE_FAILED = 1  # some episode raised (a row with failure_reason); gate: a regression
EXIT_USAGE = 2  # bad input: flag, config, output folder (or one another process writes)
EXIT_HARNESS = 3  # the harness could not do its job: an I/O error such as a full disk
EXIT_INTERRUPTED = 130  # Ctrl-C or SIGTERM; what finished is kept (continue with --resume)

EXIT_STATUS_HELP = """\
exit status:
  0    every episode ran cleanly (an unsuccessful episode is a result, not an error)
  1    some episode raised (a row with failure_reason; the run went on); gate: a regression
  2    bad input, nothing written (including a run folder another process is writing)
  3    harness or I/O error (e.g. the disk is full); rows already recorded are kept
  130  interrupted (Ctrl-C or SIGTERM); what finished is kept, continue with --resume
"""


# The harness's own top-level packages, side by side in a clone or site-packages.
OWN_PACKAGES = ("adapters", "harness", "policies", "results")
_NO_MODULE = re.compile(r"^ModuleNotFoundError: No module named '([^']+)'")


def vanished_module(name: str | None) -> str | None:
    """The cause, in one line, when a module of the harness itself cannot be imported
    while it runs: nothing of an install is missing at start, so the package changed
    under the running process, as a non-editable `pip install ".[extra]"` does when it
    reinstalls the harness during a run. None for any other module."""
    if not name or name.split(".")[0] not in OWN_PACKAGES:
        return None
    return (
        f"module {name!r} of dvla-harness vanished while it ran: the installed package was "
        "replaced under it (a `pip install` of an extra during a run does that); install every "
        "extra before starting runs"
    )


def vanished_in(failure_reasons: Iterable[str]) -> tuple[str, int] | None:
    """(cause, episodes) for episodes that failed on a vanished module of the harness."""
    names = [m.group(1) for r in failure_reasons if (m := _NO_MODULE.match(str(r)))]
    causes = [c for c in map(vanished_module, names) if c]
    return (causes[0], len(causes)) if causes else None


class UsageError(ValueError):
    """Bad input from the user (flag, config, output folder); nothing has been written."""


class HarnessError(RuntimeError):
    """The harness could not do its job (an I/O error on the run folder, a full disk);
    one line and exit status 3. Rows recorded before it are kept."""


class InterruptedWhileSaving(KeyboardInterrupt):
    """Ctrl-C (again) while a run compacts its rows or writes its manifest: the run stops
    at once (exit 130), and the message says what is safe. Every write there is atomic
    (a temporary file renamed into place), and pending.jsonl is removed only after
    episodes.parquet holds its rows, so no recorded episode is lost."""
