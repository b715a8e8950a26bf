"""`dvla-harness show`: re-print a run's summary from its rows (finished or interrupted)."""

from __future__ import annotations

import argparse

from harness.console import console
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
    p.set_defaults(func=cmd_show)


def cmd_show(args: argparse.Namespace) -> int:
    from results.render import summary_table
    from results.store import ResultsFileError, RunDir
    from results.summary import summarize

    run_dir = RunDir(args.run_dir)
    try:
        manifest = run_dir.read_manifest()
        episodes = run_dir.read_episodes()
    except ResultsFileError as exc:
        raise UsageError(str(exc)) from None
    env = manifest.get("environment", {})
    console.print(
        f"run {manifest.get('run_id')} ({manifest.get('status')}), suite {manifest['suite']['name']}, "
        f"{len(episodes)} episodes; started {manifest.get('started_at')}; "
        f"{env.get('cpu')}, GPU {env.get('gpu') or 'none'}; git {env.get('git_commit') or 'n/a'}"
    )
    if len(episodes):
        console.print(summary_table(summarize(episodes)))
    return 0
