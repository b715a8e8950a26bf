"""`dvla-harness report`: the paper's table layout, and a self-contained HTML report."""

from __future__ import annotations

import argparse

from harness.commands.leaderboard import check_baseline, load, print_warnings
from harness.errors import UsageError

EPILOG = """\
examples:
  dvla-harness report paper-table runs/spatial runs/goal runs/object runs/long
  dvla-harness report paper-table runs/a --baseline bidirectional > table.md
  dvla-harness report html runs/a runs/b --out report/
  dvla-harness report html runs/a --out report/ --overwrite   # replace an earlier report
  dvla-harness report paper-table runs/state-based --allow-privileged   # labelled [privileged state]

paper-table prints Markdown: rows = policy configurations, columns = success per suite
(Wilson 95%), average, tokens/s and speedup measured here; then the published Fast-dVLA
rows in a section of their own (their tokens/s and speedups are the paper's), labelled
with their source. Runs with no LIBERO, chain or SimplerEnv-like suite exit 2. html writes OUT/index.html (one self-contained page:
sortable leaderboards, the paper table, a Pareto plot, provenance of every run) plus
leaderboard.md, leaderboard.csv and paper-table.md. See docs/reports.md.

An instruction-chain suite (chains/...) gets its own table in the layout of Fast-dVLA's
CALVIN table (reaching 1/5 ... 5/5, avg len, tokens/s, speedup), the published CALVIN
rows in a section beneath, labelled "CALVIN: not comparable" (CALVIN-like suites on LIBERO scenes).

The published LIBERO rows come from models that read camera images. LIBERO rows
measured on privileged state (obs=state, the default, or obs=images: object and fixture
poses) are refused beside them (exit 2) unless --allow-privileged is given; they are
then printed labelled [privileged state]. Rows measured with obs=upstream need no flag:
a policy that reads what the published models read (two cameras and proprioception),
served (--policy remote:url=...) or plugged in.
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "report",
        help="paper-style table or a self-contained HTML report from runs",
        description="Reports built from run folders (or episodes .parquet files).",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    kinds = p.add_subparsers(dest="kind", metavar="KIND", required=True)
    paper = kinds.add_parser(
        "paper-table",
        help="Markdown table in the layout of Fast-dVLA's LIBERO table",
        description="Rows = policy configurations, columns = success per suite, average, tokens/s, speedup; published rows beneath.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    web = kinds.add_parser(
        "html",
        help="a static, self-contained HTML report folder",
        description="Write OUT/index.html (opens offline) with leaderboards, the paper table, figures and provenance.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    for q in (paper, web):
        q.add_argument("runs", nargs="+", metavar="RUN_DIR", help="run folders or episodes .parquet files")
        q.add_argument(
            "--baseline", metavar="POLICY", help="policy or config id for speedups (default: bidirectional)"
        )
        q.add_argument(
            "--allow-privileged",
            action="store_true",
            help="print LIBERO rows measured on privileged state (obs=state or obs=images) in the "
            "table of published image-based rows, labelled [privileged state]",
        )
    web.add_argument("--out", required=True, metavar="DIR", help="report folder to write")
    web.add_argument("--overwrite", action="store_true", help="replace an earlier report in OUT")
    paper.set_defaults(func=cmd_paper_table)
    web.set_defaults(func=cmd_html)


def cmd_paper_table(args: argparse.Namespace) -> int:
    from harness.console import console
    from results.paper_table import NO_PUBLISHED_TABLE, blocks_markdown, paper_blocks, paper_table
    from results.published import PrivilegedRowsError

    runs = load(args.runs)
    check_baseline(runs, args.baseline)
    table = paper_table(runs, args.baseline)
    try:
        blocks = paper_blocks(table, args.allow_privileged)
    except PrivilegedRowsError as exc:
        raise UsageError(str(exc)) from None
    if not blocks:  # a report with nothing to show is an error a script must see
        suites = sorted({s for r in runs for s in r.episodes["suite"].unique()})
        raise UsageError(f"{', '.join(suites) or 'no rows'}: {NO_PUBLISHED_TABLE}")
    from harness.commands.leaderboard import generalization_gaps
    from results.generalization import gap_markdown

    gaps = generalization_gaps(runs)
    console.file.write(blocks_markdown(blocks) + ("\n" + gap_markdown(gaps) if gaps else ""))
    console.file.flush()
    print_warnings(table.warnings)
    return 0


def cmd_html(args: argparse.Namespace) -> int:
    from harness.console import console
    from results.html_report import ReportError, check_out, write_report
    from results.published import PrivilegedRowsError

    try:
        check_out(args.out, args.overwrite)  # before reading runs: a bad --out is the cheaper error
        runs = load(args.runs)
        check_baseline(runs, args.baseline)
        out, warnings = write_report(runs, args.out, args.baseline, args.overwrite, args.allow_privileged)
    except (ReportError, PrivilegedRowsError) as exc:
        raise UsageError(str(exc)) from None
    console.print(f"wrote {out / 'index.html'}")
    print_warnings(warnings)
    return 0
