"""Terminal rendering of summaries: what `run` prints at the end and `show` re-prints."""

from __future__ import annotations

import math

import pandas as pd
from rich.table import Table


def _num(value: float, fmt: str) -> str:
    return "-" if value is None or (isinstance(value, float) and math.isnan(value)) else format(value, fmt)


def success_cell(row: pd.Series) -> str:
    rate = _num(row["success_rate"] * 100, ".1f")
    low, high = _num(row["success_low"] * 100, ".0f"), _num(row["success_high"] * 100, ".0f")
    return f"{rate}% [{low}, {high}] ({row['successes']}/{row['episodes']})"


def summary_table(summary: pd.DataFrame, title: str = "") -> Table:
    table = Table(title=title or None, show_lines=False)
    for name, justify in (
        ("policy", "left"),
        ("task", "left"),
        ("success (Wilson 95%)", "right"),
        ("NFE/chunk", "right"),
        ("tokens/s", "right"),
        ("control Hz", "right"),
        ("wall s/episode", "right"),
        ("errors", "right"),
        ("speedup", "right"),
    ):
        table.add_column(name, justify=justify)  # type: ignore[arg-type]
    # Speedup in tokens/s over the `bidirectional` rows of the same task, when present.
    base = (
        summary[summary["policy"] == "bidirectional"]
        .drop_duplicates("task")
        .set_index("task")["tokens_per_s"]
    )
    previous = None
    for _, row in summary.iterrows():
        is_all = row["task"] == "ALL"
        policy = row["policy"] if row["policy_config_id"] != previous else ""
        previous = row["policy_config_id"]
        cells = [
            policy,
            "[b]ALL[/b]" if is_all else row["task"],
            success_cell(row),
            _num(row["nfe_per_chunk"], ".1f"),
            _num(row["tokens_per_s"], ".0f"),
            _num(row["control_hz"], ".0f"),
            _num(row["wall_clock_s"], ".2f"),
            str(row["failures"]),
            _num(row["tokens_per_s"] / base[row["task"]], ".2f") + "x" if row["task"] in base else "-",
        ]
        table.add_row(*cells, style="bold" if is_all else None, end_section=is_all)
    return table
