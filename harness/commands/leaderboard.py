"""`dvla-harness leaderboard`: several runs combined into one table per suite."""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

from harness.errors import UsageError

FORMATS = ("md", "csv", "html")
SUFFIXES = {".md": "md", ".markdown": "md", ".csv": "csv", ".html": "html", ".htm": "html"}

EPILOG = """\
examples:
  dvla-harness leaderboard runs/a runs/b                 # rich table per suite, warnings on stderr
  dvla-harness leaderboard runs/a runs/b --baseline fast_dllm
  dvla-harness leaderboard runs/* --format md --out leaderboard.md
  dvla-harness leaderboard runs/a/episodes.parquet --format csv > board.csv

Rows are policy configurations (one per machine they were timed on); success has a
Wilson 95% interval and episode counts; speedup is tokens/s over the baseline's on the
same machine, else the cell says why it is missing. Differences that move scores
(simulator/mujoco versions, render backend, seeds, episode counts) are printed as
warnings. An instruction-chain suite (chains/...) is laid out as CALVIN's table:
chains reaching 1/5 ... 5/5 and the average length (docs/chains.md). Runs of a LIBERO
suite and its LIBERO-PRO perturbations (libero/spatial:perturb=swap) add a table of
generalization gaps: the drop from the standard suite with a 95% interval, paired by
task and episode where they match (docs/libero-pro.md). See docs/reports.md.
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "leaderboard",
        help="combine runs into one table per suite (success, NFE, tokens/s, Hz, speedup)",
        description="Combine run folders (or episodes .parquet files) into one leaderboard per suite.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("runs", nargs="+", metavar="RUN_DIR", help="run folders or episodes .parquet files")
    p.add_argument(
        "--baseline",
        metavar="POLICY",
        help="policy name or policy_config_id that speedups are relative to (default: bidirectional)",
    )
    p.add_argument("--format", choices=FORMATS, help="md, csv or html (default: a terminal table)")
    p.add_argument("--out", metavar="FILE", help="write here (atomically) instead of stdout")
    from harness.console import add_wide_argument

    add_wide_argument(p)
    p.set_defaults(func=cmd_leaderboard)


def load(paths: Sequence[str]) -> list:
    """The runs, or a UsageError naming the first unusable path."""
    from results.runs import load_runs
    from results.store import ResultsFileError

    seen: set[Path] = set()
    for path in paths:
        resolved = Path(path).resolve()
        if resolved in seen:
            raise UsageError(f"{path} is given twice")
        seen.add(resolved)
    try:
        return load_runs(paths)
    except ResultsFileError as exc:
        raise UsageError(str(exc)) from None


def check_baseline(runs: Sequence, baseline: str | None) -> None:
    if baseline is None:
        return
    import pandas as pd

    rows = pd.concat([r.episodes[["policy", "policy_config_id"]] for r in runs])
    if baseline not in set(rows["policy"]) | set(rows["policy_config_id"]):
        valid = ", ".join(sorted(set(rows["policy"])))
        raise UsageError(f"--baseline {baseline!r} is not in these runs; their policies: {valid}")


def output_format(fmt: str | None, out: str | None) -> str | None:
    """--format, else the --out suffix, else None (terminal table)."""
    if fmt or not out:
        return fmt
    suffix = Path(out).suffix.lower()
    if suffix not in SUFFIXES:
        raise UsageError(f"--out {out!r}: cannot tell the format from its suffix; pass --format md|csv|html")
    return SUFFIXES[suffix]


def check_out_file(out: str) -> Path:
    path = Path(out)
    if path.is_dir():
        raise UsageError(f"--out {out!r} is a folder; give a file name")
    if not path.parent.is_dir():
        raise UsageError(f"--out {out!r}: folder {str(path.parent)!r} does not exist")
    return path


def print_warnings(warnings: Sequence[str]) -> None:
    from harness.console import print_note

    for w in warnings:
        print_note("[yellow]warning:[/yellow]", w)


def generalization_gaps(runs: Sequence) -> list:
    """The LIBERO-PRO gap tables of runs that include perturbed suites (results/generalization.py)."""
    from results.generalization import gap_tables
    from results.leaderboard import config_labels
    from results.runs import combined_episodes

    episodes = combined_episodes(runs)
    return gap_tables(episodes, config_labels(episodes))


def cmd_leaderboard(args: argparse.Namespace) -> int:
    from harness.console import console, print_table
    from results.leaderboard import board_fit, leaderboards, rich_table, to_csv, to_markdown

    fmt = output_format(args.format, args.out)
    out = check_out_file(args.out) if args.out else None
    runs = load(args.runs)
    check_baseline(runs, args.baseline)
    boards = leaderboards(runs, args.baseline)
    gaps = generalization_gaps(runs)
    warnings = [f"{b.suite}: {w}" for b in boards for w in b.warnings]
    if fmt is None:
        from results.generalization import gap_rich

        for board in boards:
            print_table(rich_table(board), fit=board_fit(board), wide=args.wide)
        for table in gaps:
            print_table(gap_rich(table), wide=args.wide)
        print_warnings(warnings)
        return 0
    if fmt == "md":
        from results.generalization import gap_markdown

        text = to_markdown(boards) + ("\n" + gap_markdown(gaps) if gaps else "")
    elif fmt == "csv":
        text = to_csv(boards)
    else:
        from results.generalization import gap_blocks
        from results.html_report import render_page

        text = render_page(
            runs, boards, title="dvla-harness leaderboard", figures=False, extra=gap_blocks(gaps)
        )
    if out is None:
        console.file.write(text)
        console.file.flush()
    else:
        from results.store import atomic_write

        atomic_write(out, text.encode())
        console.print(f"wrote {out}")
    print_warnings(warnings)
    return 0
