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

import numpy as np
import pandas as pd
from rich.table import Table

from results.render import _num
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


def _chain_row(mine: pd.DataFrame, max_length: int) -> dict[str, object]:
    lengths = mine["subtasks_completed"].to_numpy(dtype=float)
    n = len(lengths)
    row: dict[str, object] = {"chains": n}
    for k in range(1, max_length + 1):
        reached = int((lengths >= k).sum())
        low, high = wilson_interval(reached, n)
        row |= {f"reach_{k}": reached / n, f"reach_{k}_low": low, f"reach_{k}_high": high}
    low, high = length_interval(lengths)
    return row | {
        "avg_len": float(lengths.mean()),
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


def _pct(row: pd.Series, k: int) -> str:
    return f"{row[f'reach_{k}'] * 100:.1f} [{row[f'reach_{k}_low'] * 100:.0f}, {row[f'reach_{k}_high'] * 100:.0f}]"


def chain_table(summary: pd.DataFrame, title: str = "") -> Table:
    """CALVIN's layout: % of chains reaching 1/5 ... 5/5 (Wilson 95%), average length
    (bootstrap 95%), then NFE per chunk, tokens/s and speedup over bidirectional."""
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
        table.add_column(name, justify="left" if name in ("policy", "scene") else "right")
    base = (
        summary[summary["policy"] == "bidirectional"]
        .drop_duplicates("task")
        .set_index("task")["tokens_per_s"]
    )
    previous = None
    for _, row in summary.iterrows():
        base_speed = float(base[row["task"]]) if row["task"] in base.index else math.nan
        policy = str(row["policy"]) if row["policy_config_id"] != previous else ""
        previous = row["policy_config_id"]
        length = f"{row['avg_len']:.2f} [{row['avg_len_low']:.2f}, {row['avg_len_high']:.2f}]"
        speedup = _num(row["tokens_per_s"] / base_speed, ".2f")
        table.add_row(
            policy,
            str(row["task"]),
            str(row["chains"]),
            *(_pct(row, k) for k in range(1, 6)),
            length,
            _num(row["nfe_per_chunk"], ".1f"),
            _num(row["tokens_per_s"], ".0f"),
            "-" if speedup == "-" else speedup + "x",
        )
    return table
