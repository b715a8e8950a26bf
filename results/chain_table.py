"""The CALVIN table of instruction-chain runs: how many chains reach 1/5 ... 5/5, and
the average length, with the decoder's speed beside them (as Fast-dVLA's CALVIN table).

Reaching k/5 is a proportion of chains, so it gets the Wilson interval like every other
success rate here. The average length is a mean of a bounded count (0-5) whose
distribution is lumpy (most chains stop at 0 or run to 5), so its interval is a
percentile bootstrap over chains with a fixed seed: the same rows always print the same
interval, and it needs no normality that a 10-chain run does not have.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd
from rich.table import Table

from results.render import Cell, _num, finite_or_none
from results.summary import wilson_interval

BOOTSTRAP_RESAMPLES = 10_000
BOOTSTRAP_SEED = 0


def is_chain_run(episodes: pd.DataFrame) -> bool:
    return "subtasks_completed" in episodes and episodes["subtasks_completed"].notna().any()


def length_interval(lengths: np.ndarray) -> tuple[float, float]:
    """Percentile bootstrap 95% interval of the mean chain length; (nan, nan) when empty."""
    if len(lengths) == 0:
        return (math.nan, math.nan)
    rng = np.random.default_rng(BOOTSTRAP_SEED)
    means = rng.choice(lengths, size=(BOOTSTRAP_RESAMPLES, len(lengths)), replace=True).mean(axis=1)
    low, high = np.percentile(means, [2.5, 97.5])
    return (float(low), float(high))


def reach_text(rate: float, low: float, high: float) -> str:
    """'80.0 [49, 94]': percent of chains reaching k, Wilson 95% bounds."""
    return f"{rate * 100:.1f} [{low * 100:.0f}, {high * 100:.0f}]"


def length_text(mean: float, low: float, high: float) -> str:
    """'3.00 [1.70, 4.20]': average length, bootstrap 95% bounds."""
    return f"{mean:.2f} [{low:.2f}, {high:.2f}]"


@dataclass(frozen=True)
class ChainStats:
    """A set of chains in CALVIN's terms: how many reach k of 5, and the average length.
    The one place these numbers are computed: `run`/`show`, leaderboards, paper tables
    and the HTML report all read them from here."""

    chains: int
    reached: tuple[int, ...]  # chains reaching k subtasks, k = 1 .. max length
    avg_len: float
    avg_len_interval: tuple[float, float]

    def reach(self, k: int) -> float:
        return self.reached[k - 1] / self.chains if self.chains else math.nan

    def reach_interval(self, k: int) -> tuple[float, float]:
        return wilson_interval(self.reached[k - 1], self.chains)

    def reach_text(self, k: int) -> str:
        return reach_text(self.reach(k), *self.reach_interval(k)) if self.chains else "-"

    def length_text(self) -> str:
        return length_text(self.avg_len, *self.avg_len_interval) if self.chains else "-"


def chain_stats(lengths: np.ndarray | pd.Series, max_length: int = 5) -> ChainStats:
    """From subtasks completed per chain; a chain whose row failed (an exception) counts
    as the subtasks it completed before it."""
    lengths = np.asarray(lengths, dtype=float)
    reached = tuple(int((lengths >= k).sum()) for k in range(1, max_length + 1))
    mean = float(lengths.mean()) if len(lengths) else math.nan
    return ChainStats(len(lengths), reached, mean, length_interval(lengths))


def _chain_row(mine: pd.DataFrame, max_length: int) -> dict[str, object]:
    stats = chain_stats(mine["subtasks_completed"], max_length)
    row: dict[str, object] = {"chains": stats.chains}
    for k in range(1, max_length + 1):
        low, high = stats.reach_interval(k)
        row |= {f"reach_{k}": stats.reach(k), f"reach_{k}_low": low, f"reach_{k}_high": high}
    low, high = stats.avg_len_interval
    return row | {
        "avg_len": stats.avg_len,
        "avg_len_low": low,
        "avg_len_high": high,
        "nfe_per_chunk": mine["nfe_per_chunk"].mean(),
        "tokens_per_s": mine["tokens_per_s"].mean(),
    }


def chain_summary(episodes: pd.DataFrame, max_length: int = 5) -> pd.DataFrame:
    """Per policy configuration, one row per scene (task) and, with several scenes, an
    `ALL` row: reach_k (k = 1..5) with Wilson bounds, avg_len with a bootstrap interval,
    NFE per chunk and tokens/s. A chain whose row failed (an exception) counts as the
    subtasks it completed before it."""
    chains = episodes[episodes["subtasks_completed"].notna()]
    if "task" not in chains:
        chains = chains.assign(task="ALL")
    first = chains.sort_values("started_at", kind="stable") if "started_at" in chains else chains
    rows = []
    for config_id, policy in first.drop_duplicates("policy_config_id")[
        ["policy_config_id", "policy"]
    ].itertuples(index=False):
        mine = chains[chains["policy_config_id"] == config_id]
        tasks = list(dict.fromkeys(mine["task"]))
        for task in tasks:
            key = {"policy_config_id": config_id, "policy": policy, "task": task}
            rows.append(key | _chain_row(mine[mine["task"] == task], max_length))
        if len(tasks) > 1:
            rows.append(
                {"policy_config_id": config_id, "policy": policy, "task": "ALL"}
                | _chain_row(mine, max_length)
            )
    return pd.DataFrame(rows)


def chain_table(summary: pd.DataFrame, title: str = "", labels: dict[str, str] | None = None) -> Table:
    """CALVIN's layout: % of chains reaching 1/5 ... 5/5 (Wilson 95%), average length
    (bootstrap 95%), then NFE per chunk, tokens/s and speedup over bidirectional.
    `labels` (policy_config_id -> config_label) name each configuration as the summary
    table does, so several settings of one policy read apart."""
    table = Table(
        title=title or None,
        caption="chains reaching k of 5 subtasks, % (Wilson 95%); avg len: subtasks completed per "
        "chain (bootstrap 95%); CALVIN's protocol on LIBERO scenes, not CALVIN (docs/chains.md)",
    )
    for name in (
        "policy",
        "scene",
        "chains",
        "1/5",
        "2/5",
        "3/5",
        "4/5",
        "5/5",
        "avg len",
        "NFE/chunk",
        "tokens/s",
        "speedup",
    ):
        table.add_column(name, justify="left" if name in ("policy", "scene") else "right", overflow="fold")
    base = (
        summary[summary["policy"] == "bidirectional"]
        .drop_duplicates("task")
        .set_index("task")["tokens_per_s"]
    )
    previous = None
    for _, row in summary.iterrows():
        base_speed = float(base[row["task"]]) if row["task"] in base.index else math.nan
        name = (labels or {}).get(row["policy_config_id"], str(row["policy"]))
        policy = name if row["policy_config_id"] != previous else ""
        previous = row["policy_config_id"]
        length = length_text(row["avg_len"], row["avg_len_low"], row["avg_len_high"])
        speedup = _num(row["tokens_per_s"] / base_speed, ".2f")
        table.add_row(
            policy,
            str(row["task"]),
            str(row["chains"]),
            *(
                reach_text(row[f"reach_{k}"], row[f"reach_{k}_low"], row[f"reach_{k}_high"])
                for k in range(1, 6)
            ),
            length,
            _num(row["nfe_per_chunk"], ".1f"),
            _num(row["tokens_per_s"], ".0f"),
            "-" if speedup == "-" else speedup + "x",
        )
    return table


# --- cells for leaderboards (results/leaderboard.py) -------------------------------------


def chain_cells(
    chain: ChainStats | None, groups_stats: dict[str, ChainStats], groups: Sequence[str], k_max: int
) -> list[Cell]:
    """Average length per scene (with several), reaching 1/k_max ... k_max/k_max, average length."""
    if chain is None:  # a row of a chain suite without chain columns: none in practice
        return [Cell("-", None)] * ((len(groups) if len(groups) > 1 else 0) + k_max + 1)
    per_group = [
        Cell(groups_stats[g].length_text(), finite_or_none(groups_stats[g].avg_len))
        if g in groups_stats
        else Cell("-", None)
        for g in groups
    ]
    return [
        *(per_group if len(groups) > 1 else []),
        *(Cell(chain.reach_text(k), finite_or_none(chain.reach(k))) for k in range(1, k_max + 1)),
        Cell(chain.length_text(), finite_or_none(chain.avg_len)),
    ]


def chain_columns(chain: ChainStats | None, groups_stats: dict[str, ChainStats]) -> dict[str, Any]:
    """The same numbers as frame columns (rates as fractions), for CSV and notebooks."""
    assert chain is not None
    out: dict[str, Any] = {}
    for k in range(1, len(chain.reached) + 1):
        low, high = chain.reach_interval(k)
        out |= {f"reach_{k}": chain.reach(k), f"reach_{k}_low": low, f"reach_{k}_high": high}
    low, high = chain.avg_len_interval
    out |= {"avg_len": chain.avg_len, "avg_len_low": low, "avg_len_high": high}
    for group, stats in groups_stats.items():
        out[f"avg_len[{group}]"] = stats.avg_len
    return out


# --- where chains fail, from the per-subtask records --------------------------------------


def subtask_failures(episodes: pd.DataFrame) -> pd.DataFrame:
    """Per policy configuration and subtask id: how often the subtask was attempted, how
    each attempt ended (the records' `outcome`: completed, out_of_steps,
    goal_held_at_start, in_progress), and the median steps of the completed ones. Read
    from the rows' `subtasks` records alone, so the breakdown of a run is reproducible
    without re-running it. A failed record written before outcomes were recorded (null)
    counts as `unrecorded`."""
    rows = []
    chains = episodes[episodes["subtasks"].notna()] if "subtasks" in episodes else episodes.iloc[:0]
    for config_id, records in zip(chains["policy_config_id"], chains["subtasks"], strict=True):
        for r in records:
            outcome = r.get("outcome")
            if outcome is None:  # a row from before the credit rule: steps 0 = never reached
                if not r["steps"]:
                    continue
                outcome = "completed" if r["success"] else "unrecorded"
            if outcome == "not_reached":
                continue
            rows.append(
                {
                    "policy_config_id": config_id,
                    "subtask": r["id"],
                    "outcome": outcome,
                    "steps": r["steps"] if outcome == "completed" else math.nan,
                }
            )
    columns = ["policy_config_id", "subtask", "attempts", "completed", "out_of_steps"]
    columns += ["goal_held_at_start", "in_progress", "unrecorded", "median_steps_completed"]
    if not rows:
        return pd.DataFrame(columns=columns)
    frame = pd.DataFrame(rows)
    counts = pd.crosstab([frame["policy_config_id"], frame["subtask"]], frame["outcome"])
    counts = counts.reindex(columns=columns[3:-1], fill_value=0)
    counts.columns.name = None
    counts.insert(0, "attempts", counts.sum(axis=1))
    median = frame.groupby(["policy_config_id", "subtask"])["steps"].median()
    return counts.assign(median_steps_completed=median).reset_index()[columns]
