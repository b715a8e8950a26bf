"""`dvla-harness plot`: ablation, Pareto and decoding-order figures from run folders."""

from __future__ import annotations

import argparse
from typing import Any

from harness.errors import UsageError

EXAMPLES = """\
examples:
  dvla-harness plot ablation runs/sweep --x block_size --y success,tokens_per_s --hue tau_conf --out fig.png
  dvla-harness plot ablation runs/noise --x block_size --y success --hue noise_schedule --out noise.svg
  dvla-harness plot pareto runs/sweep runs/main --x tokens_per_s --y success --out pareto.svg
  dvla-harness plot ablation runs/blocks --x block_size --y success,speedup --out blocks.png  # a sweep with --reference
  dvla-harness plot pareto runs/blocks --x speedup --out blocks.svg
  dvla-harness plot decoding-order runs/sweep --out order.png     # needs a run made with --traces
  dvla-harness plot latency runs/none runs/p2-sync runs/p2-async runs/p4-sync --out latency.png

Columns: episode-table columns (docs/results-schema.md), policy parameters (block_size,
tau_conf, steps_per_block, ...; `param.NAME` when an episode column has the same name,
e.g. param.steps) and checkpoint-header fields (recipe, noise_schedule, pattern,
train_steps; `checkpoint.NAME`), and `speedup`: tokens/s over --baseline's on the same
episodes of the same run. Output: .png or .svg, written atomically.
"""


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "plot",
        help="figures from run folders: ablation lines, speed/success Pareto, decoding order, latency",
        description="Draw a figure from one or more run folders (or episodes .parquet files).",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    kinds = p.add_subparsers(dest="kind", metavar="KIND", required=True)
    a = kinds.add_parser(
        "ablation",
        help="y against x, a line per hue value, 95%% intervals",
        description="One panel per --y column against --x; a line per --hue value; "
        "95% intervals (Wilson for success, t for means of rates).",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    a.add_argument("--x", required=True, help="column on the x axis, e.g. block_size")
    a.add_argument(
        "--y", required=True, metavar="COL,...", help="one panel per column, e.g. success,tokens_per_s"
    )
    a.add_argument("--hue", help="a line per value of this column, e.g. noise_schedule")
    q = kinds.add_parser(
        "pareto",
        help="speed/success frontier, one marker per policy configuration",
        description="Each policy configuration's mean x and y with 95% intervals, and the "
        "frontier of configurations no other beats on both.",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    q.add_argument("--x", default="tokens_per_s", help="default tokens_per_s")
    q.add_argument("--y", default="success", help="default success")
    d = kinds.add_parser(
        "decoding-order",
        help="heat map of which action position each forward pass commits",
        description="From OUT/traces.jsonl (runs made with --traces): per configuration, how "
        "often each action position is committed at each forward pass of a chunk.",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    lat = kinds.add_parser(
        "latency",
        help="success against inference latency, a line per decoder and execution",
        description="Runs at several --inference-latency modes (and `none`): y against the mode, "
        "a line per policy configuration and execution, 95% intervals (docs/latency.md).",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    lat.add_argument(
        "--y", default="success", metavar="COL,...", help="default success; e.g. success,hold_steps"
    )
    for kind in (a, q):
        kind.add_argument(
            "--baseline",
            default="bidirectional",
            metavar="POLICY",
            help="policy or config id that `speedup` is over, paired episode by episode with rows of "
            "the same run (a sweep's --reference; default bidirectional); ablation draws it as a line",
        )
    for kind in (a, q, d, lat):
        kind.add_argument("runs", nargs="+", metavar="RUN_DIR", help="run folder(s) or episodes .parquet")
        kind.add_argument("--out", required=True, metavar="FILE.png|FILE.svg", help="figure to write")
        kind.set_defaults(func=cmd_plot)


def _checkpoint_fields(runs: list[Any]) -> dict[str, dict[str, Any]]:
    """Per policy configuration, the checkpoint-header fields its run's manifest recorded."""
    fields: dict[str, dict[str, Any]] = {}
    for run in runs:
        for entry in run.manifest.get("policies", []):
            if entry.get("checkpoint_fields"):
                fields[entry["config_id"]] = entry["checkpoint_fields"]
    return fields


def cmd_plot(args: argparse.Namespace) -> int:
    from harness.console import console
    from results import plots
    from results.runs import combined_episodes, load_runs
    from results.store import ResultsFileError, RunDir

    try:
        plots.check_out(args.out)  # before any reading: a bad suffix costs nothing
        runs = load_runs(args.runs)
        episodes = plots.plot_frame(combined_episodes(runs), _checkpoint_fields(runs))
        if args.kind == "ablation":
            ys = [c.strip() for c in args.y.split(",") if c.strip()]
            plots.ablation_plot(episodes, args.x, ys, args.hue, out=args.out, baseline=args.baseline)
        elif args.kind == "latency":
            from results.latency_plot import latency_plot

            latency_plot(episodes, [c.strip() for c in args.y.split(",") if c.strip()], out=args.out)
        elif args.kind == "pareto":
            plots.pareto_plot(episodes, args.x, args.y, out=args.out, baseline=args.baseline)
        else:
            untraced = [r for r in runs if not RunDir(r.path).has_traces()]
            silent = [r for r in untraced if (r.manifest or {}).get("traces")]  # asked, got none
            if silent:
                policies = sorted(
                    set(episodes.loc[episodes["run"].isin([r.label for r in silent]), "policy"])
                )
                raise plots.PlotInputError(
                    f"{', '.join(str(r.path) for r in silent)}: no traces.jsonl, though made with --traces: "
                    f"its policies ({', '.join(policies)}) returned no decode trace (only the dVLA "
                    "decoders report one), or the file was removed"
                )
            untraced = [str(r.path) for r in untraced]
            if untraced:
                raise plots.PlotInputError(
                    f"{', '.join(untraced)}: no traces.jsonl; record decode traces with "
                    "`dvla-harness run ... --traces` (or `sweep ... --traces`)"
                )
            traces = _traces(runs, episodes)
            from results.order_plot import decoding_order_plot

            decoding_order_plot(traces, out=args.out)
    except (plots.PlotInputError, ResultsFileError) as exc:
        raise UsageError(str(exc)) from None
    console.print(f"wrote {args.out}")
    return 0


def _traces(runs: list[Any], episodes: Any) -> Any:
    import pandas as pd

    from results.store import RunDir

    traces = pd.concat([RunDir(r.path).read_traces() for r in runs], ignore_index=True)
    configs = episodes.drop_duplicates("policy_config_id").set_index("policy_config_id")
    traces["config_label"] = traces["policy_config_id"].map(configs["config_label"])
    if "param.block_size" in configs:
        traces["block_size"] = traces["policy_config_id"].map(configs["param.block_size"])
    return traces
