"""`dvla-harness show`: re-print a run's summary from its rows (finished or interrupted)."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from harness.console import add_wide_argument, console, print_note, print_table
from harness.errors import UsageError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "show",
        help="re-print a run's summary from its Parquet rows",
        description="Summarise a run folder (finished or interrupted) from its episode rows.",
        epilog="example:\n  dvla-harness show runs/demo",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("run_dir", metavar="RUN_DIR")
    add_wide_argument(p)
    p.set_defaults(func=cmd_show)


def cmd_show(args: argparse.Namespace) -> int:
    from results.labels import row_labels
    from results.render import summary_fit, summary_table
    from results.runs import speed_warning
    from results.store import ResultsFileError, RunDir
    from results.summary import summarize

    run_dir = RunDir(args.run_dir)
    run_dir.remove_temporaries_unless_locked()  # what a killed writer left, as results.runs.load_run
    try:
        manifest = run_dir.read_manifest()
        episodes = run_dir.read_episodes()
    except ResultsFileError as exc:
        raise UsageError(str(exc)) from None
    env = manifest.get("environment") or {}
    # a manifest lacking a field says less about the run; the rows still say what ran
    suite = (manifest.get("suite") or {}).get("name") or ", ".join(sorted(set(episodes["suite"]))) or "?"
    status = manifest.get("status")
    if status == "running" and not _writer_alive(run_dir.path):
        status = "interrupted or killed: no process is writing it; finish it with --resume"
    console.print(
        f"run {manifest.get('run_id', '?')} ({status or 'status unknown'}), suite {suite}, "
        f"{len(episodes)} episodes; started {manifest.get('started_at')}; "
        f"{env.get('cpu')}, GPU {env.get('gpu') or 'none'}; git {env.get('git_commit') or 'n/a'}"
    )
    if warning := speed_warning(manifest):
        print_note(
            "[yellow]warning:[/yellow]", f"speed figures of this run are unreliable: {warning}", console
        )
    if len(episodes):
        from harness.commands.run import print_chain_table, print_latency_table, print_out_of_space

        labels = row_labels(episodes)  # the names the rows hold, as `run` printed them
        summary = summarize(episodes)
        print_table(summary_table(summary, labels=labels), fit=summary_fit(summary, episodes), wide=args.wide)
        print_chain_table(episodes, labels, args.wide)
        print_latency_table(episodes, labels, args.wide)
        print_out_of_space(episodes, labels)
    return 0


def _writer_alive(folder: Path) -> bool:
    """Whether a live process holds the folder's writer lock (results.lock.RunLock):
    a manifest says "running" from start to finish, and a killed run cannot change it."""
    import fcntl

    from results.lock import RunLock

    try:
        fd = os.open(RunLock(folder).path, os.O_RDONLY | os.O_CLOEXEC | os.O_NONBLOCK)  # a FIFO: no wait
    except FileNotFoundError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    except OSError:
        return True  # cannot tell: say nothing new
    finally:
        os.close(fd)
    return False
