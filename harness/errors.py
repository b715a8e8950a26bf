"""Errors the CLI turns into one clear line, and the exit statuses every command uses."""

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
