"""Terminal rendering of summaries: what `run` prints at the end and `show` re-prints."""

from __future__ import annotations

import math
from dataclasses import dataclass

import pandas as pd
from rich.table import Table

from results.table_fit import ALWAYS, Fit


@dataclass(frozen=True)
class Cell:
    """A formatted table cell and what it sorts by (numbers sort numerically): the one
    layout unit that terminal, Markdown, CSV and HTML outputs share."""

    text: str
    value: float | str | None


def finite_or_none(value: float) -> float | None:
    return None if value is None or math.isnan(value) else float(value)


def number_cell(value: float, fmt: str) -> Cell:
    v = finite_or_none(value)
    return Cell("-" if v is None else format(v, fmt), v)


def _num(value: float, fmt: str) -> str:
    return "-" if value is None or (isinstance(value, float) and math.isnan(value)) else format(value, fmt)


def success_cell(row: pd.Series) -> str:
    rate = _num(row["success_rate"] * 100, ".1f")
    low, high = _num(row["success_low"] * 100, ".0f"), _num(row["success_high"] * 100, ".0f")
    return f"{rate}% [{low}, {high}] ({row['successes']}/{row['episodes']})"


# Fewer episodes than this on either side and a per-task speedup is noise (one slow
# episode moves it by tens of percent); the ALL row always has one.
MIN_EPISODES_FOR_TASK_SPEEDUP = 10
NO_BASELINE = "n/a: no bidirectional row"  # as results.leaderboard.speedups says it
NO_TOKENS = "n/a: no tokens"  # a policy that decodes no tokens (a scripted expert)
BASELINE_NO_TOKENS = "n/a: baseline decodes no tokens"
# What each speed column means, printed beneath the columns a table shows.
NOTES = {
    "control Hz": "control Hz: env steps per second of policy time (the policy alone)",
    "loop Hz": "loop Hz: env steps per second of wall-clock (policy + simulator + harness)",
    "GFLOP/chunk": "GFLOP/chunk: counted work of the passes behind one chunk (harness/episode/work.py; - not measured)",
    "speedup vs bidirectional": "speedup: tokens/s over bidirectional's in this run "
    f"(per task only with >= {MIN_EPISODES_FOR_TASK_SPEEDUP} episodes each)",
}
CAPTION = "; ".join(NOTES.values())


# What a narrow terminal keeps first (results/table_fit.py): who, where and how often it
# succeeded, then the speed that the harness exists to measure, then the rest.
SUMMARY_RANKS = {
    "policy": ALWAYS,
    "task": ALWAYS,
    "success (Wilson 95%)": ALWAYS,
    "speedup vs bidirectional": 10,
    "tokens/s": 20,
    "NFE/chunk": 30,
    "errors": 40,
    "wall s/episode": 50,
    "control Hz": 60,
    "loop Hz": 70,
    "GFLOP/chunk": 80,
}


def task_keys(episodes: pd.DataFrame) -> dict[str, str]:
    """Task name -> "#index", the index `--tasks` and `list tasks` use: what a narrow
    terminal shows in place of a LIBERO task name (83 characters at most)."""
    if "task_index" not in episodes or "task" not in episodes:
        return {}
    pairs = episodes[["task", "task_index"]].drop_duplicates("task").sort_values("task_index")
    return {str(t): f"#{int(i)}" for t, i in pairs.itertuples(index=False)}


def summary_fit(summary: pd.DataFrame, episodes: pd.DataFrame) -> Fit:
    """How summary_table gives way to a narrow terminal; errors rank beside success when
    any episode raised (a column of zeros is the first to go)."""
    ranks = dict(SUMMARY_RANKS)
    if summary["failures"].sum() > 0:
        ranks["errors"] = 5  # its own rank (a rank is shown whole or not at all)
    return Fit(ranks, task_keys(episodes), notes=NOTES)


def _speedup(tokens_per_s: float, base: float, is_all: bool) -> str:
    """A ratio, or the leaderboard's reason for none (on the ALL row; '-' on a task's)."""
    mine, theirs = finite_or_none(tokens_per_s), finite_or_none(base)
    if mine is None:
        return NO_TOKENS if is_all else "-"
    if theirs is None or theirs <= 0:
        return BASELINE_NO_TOKENS if is_all else "-"
    return f"{mine / theirs:.2f}x"


def summary_table(summary: pd.DataFrame, title: str = "", labels: dict[str, str] | None = None) -> Table:
    """`labels` (policy_config_id -> label, results.leaderboard.config_labels) tell apart
    several configurations of one policy ("fast_dvla (tau_conf=0.3)"); else the name."""
    table = Table(title=title or None, show_lines=False, caption=CAPTION)
    for name, justify in (
        ("policy", "left"),
        ("task", "left"),
        ("success (Wilson 95%)", "right"),
        ("NFE/chunk", "right"),
        ("GFLOP/chunk", "right"),
        ("tokens/s", "right"),
        ("control Hz", "right"),
        ("loop Hz", "right"),
        ("wall s/episode", "right"),
        ("errors", "right"),
        ("speedup vs bidirectional", "right"),
    ):
        table.add_column(name, justify=justify, overflow="fold")  # type: ignore[arg-type]
    base = summary[summary["policy"] == "bidirectional"].drop_duplicates("task").set_index("task")
    previous = None
    for _, row in summary.iterrows():
        is_all = row["task"] == "ALL"
        name = (labels or {}).get(row["policy_config_id"], row["policy"])
        policy = name if row["policy_config_id"] != previous else ""
        previous = row["policy_config_id"]
        speedup = "-"
        if base.empty:
            speedup = NO_BASELINE if is_all else "-"  # the leaderboard's wording, once per policy
        elif row["task"] in base.index:
            enough = min(row["episodes"], base.loc[row["task"], "episodes"]) >= MIN_EPISODES_FOR_TASK_SPEEDUP
            if is_all or enough:
                speedup = _speedup(row["tokens_per_s"], base.loc[row["task"], "tokens_per_s"], is_all)
        cells = [
            policy,
            "[b]ALL[/b]" if is_all else row["task"],
            success_cell(row),
            _num(row["nfe_per_chunk"], ".1f"),
            _num(row.get("flops_per_chunk", math.nan) / 1e9, ".3f"),
            _num(row["tokens_per_s"], ".0f"),
            _num(row["control_hz"], ".0f"),
            _num(row.get("loop_hz", math.nan), ".0f"),
            _num(row["wall_clock_s"], ".2f"),
            str(row["failures"]),
            speedup,
        ]
        table.add_row(*cells, style="bold" if is_all else None, end_section=is_all)
    return table
