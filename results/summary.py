"""Aggregates episode rows into per-task and overall summaries with 95% intervals.

Success rates use the Wilson score interval: unlike the normal approximation it stays
inside [0, 1] and is honest at 0/n and n/n, which is where small evaluations live.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import pandas as pd

Z95 = 1.959963984540054
# Two-sided 95% Student t quantiles; between rows the smaller df is used (conservative).
_T975 = {1: 12.706, 2: 4.303, 3: 3.182, 4: 2.776, 5: 2.571, 6: 2.447, 7: 2.365, 8: 2.306, 9: 2.262,
         10: 2.228, 12: 2.179, 15: 2.131, 20: 2.086, 25: 2.060, 30: 2.042, 40: 2.021, 60: 2.000,
         120: 1.980}  # fmt: skip

SUMMARY_COLUMNS = (
    "policy_config_id",
    "policy",
    "task",
    "episodes",
    "successes",
    "success_rate",
    "success_low",
    "success_high",
    "failures",
    "nfe_per_chunk",
    "flops_per_chunk",
    "tokens_per_s",
    "control_hz",
    "loop_hz",
    "wall_clock_s",
)


def t_quantile(df: int) -> float:
    """The two-sided 95% Student t quantile for `df` degrees of freedom (the table's next
    smaller entry between rows: conservative); NaN below 1."""
    if df < 1:
        return math.nan
    return _T975[max(k for k in _T975 if k <= df)] if df <= 120 else 1.980  # t(120): conservative


def wilson_interval(successes: int, n: int, z: float = Z95) -> tuple[float, float]:
    """Wilson score interval for a binomial proportion; (nan, nan) when n == 0."""
    if n == 0:
        return (math.nan, math.nan)
    p = successes / n
    denom = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    return (max(0.0, centre - half), min(1.0, centre + half))


@dataclass(frozen=True)
class Success:
    """Successes of n episodes: a rate with its Wilson 95% interval."""

    successes: int
    episodes: int

    @property
    def rate(self) -> float:
        return self.successes / self.episodes if self.episodes else math.nan

    @property
    def interval(self) -> tuple[float, float]:
        return wilson_interval(self.successes, self.episodes)

    def text(self) -> str:
        if not self.episodes:
            return "-"
        low, high = self.interval
        return (
            f"{100 * self.rate:.1f}% [{100 * low:.0f}, {100 * high:.0f}] ({self.successes}/{self.episodes})"
        )


def _summarise(group: pd.DataFrame) -> dict[str, float]:
    n = len(group)
    k = int(group["success"].sum())
    low, high = wilson_interval(k, n)
    return {
        "episodes": n,
        "successes": k,
        "success_rate": k / n if n else math.nan,
        "success_low": low,
        "success_high": high,
        "failures": int(group["failure_reason"].notna().sum()),
        "nfe_per_chunk": group["nfe_per_chunk"].mean(),
        # counted work (harness/episode/work.py); NaN when no row measured it
        "flops_per_chunk": group["flops_per_chunk"].mean() if "flops_per_chunk" in group else math.nan,
        "tokens_per_s": group["tokens_per_s"].mean(),
        "control_hz": group["control_hz"].mean(),
        "loop_hz": group["loop_hz"].mean() if "loop_hz" in group else math.nan,
        "wall_clock_s": group["wall_clock_s"].mean(),
    }


def summarize(episodes: pd.DataFrame) -> pd.DataFrame:
    """One row per (policy configuration, task) plus an `ALL` row per configuration.

    Means of per-episode rates (tokens/s, Hz) weight every episode equally, matching
    how the papers average over trials.
    """
    rows = []
    # Configurations in the order they first ran (the order they were listed in the run).
    first = episodes.sort_values("started_at", kind="stable") if "started_at" in episodes else episodes
    order = first.drop_duplicates("policy_config_id")[["policy_config_id", "policy"]]
    for config_id, policy in order.itertuples(index=False):
        mine = episodes[episodes["policy_config_id"] == config_id]
        for task in mine.sort_values("task_index")["task"].unique():
            rows.append(
                {"policy_config_id": config_id, "policy": policy, "task": task}
                | _summarise(mine[mine["task"] == task])
            )
        rows.append({"policy_config_id": config_id, "policy": policy, "task": "ALL"} | _summarise(mine))
    return pd.DataFrame(rows, columns=list(SUMMARY_COLUMNS))
