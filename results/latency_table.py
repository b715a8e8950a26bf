"""The latency table beneath a run's summary (docs/latency.md): what each configuration's
simulated decoding time cost it, beside its success. Shown only for runs at a latency
other than `none`, where every one of these figures is 0."""

from __future__ import annotations

import pandas as pd
from rich.table import Table

from results.summary import Success

LATENCY_COLUMNS = ("delay_steps_mean", "delay_steps_max", "late_chunks", "hold_steps")


def has_latency(episodes: pd.DataFrame) -> bool:
    """Whether any row ran at an inference latency other than `none`."""
    if "inference_latency" not in episodes:
        return False
    return bool((episodes["inference_latency"].fillna("none") != "none").any())


def latency_summary(episodes: pd.DataFrame) -> pd.DataFrame:
    """One row per configuration: its latency mode, success, and per-episode means of
    the delay, late chunks and hold steps (hold share: of all its env steps)."""
    rows = []
    first = episodes.sort_values("started_at", kind="stable") if "started_at" in episodes else episodes
    for config_id, mine in first.groupby("policy_config_id", sort=False):  # in the order they ran
        steps = mine["steps"].sum()
        rows.append(
            {
                "policy_config_id": config_id,
                "policy": mine["policy"].iloc[0],
                "latency": f"{mine['inference_latency'].fillna('none').iloc[0]} {mine['execution'].fillna('sync').iloc[0]}",
                "success": Success(int(mine["success"].sum()), len(mine)).text(),
                "d_mean": mine["delay_steps_mean"].mean(),
                "d_max": mine["delay_steps_max"].max(),
                "late_per_episode": mine["late_chunks"].mean(),
                "hold_per_episode": mine["hold_steps"].mean(),
                "hold_share": mine["hold_steps"].sum() / steps if steps else float("nan"),
            }
        )
    return pd.DataFrame(rows)


def latency_table(summary: pd.DataFrame, labels: dict[str, str] | None = None) -> Table:
    table = Table(title="inference latency (docs/latency.md)")
    for name in (
        "policy",
        "latency",
        "success (Wilson 95%)",
        "d mean",
        "d max",
        "late chunks/ep",
        "hold steps/ep",
        "hold %",
    ):
        table.add_column(name, justify="left" if name in ("policy", "latency") else "right")
    for _, row in summary.iterrows():
        table.add_row(
            (labels or {}).get(row["policy_config_id"], row["policy"]),
            row["latency"],
            row["success"],
            f"{row['d_mean']:.1f}",
            f"{row['d_max']:.0f}" if pd.notna(row["d_max"]) else "-",
            f"{row['late_per_episode']:.1f}",
            f"{row['hold_per_episode']:.1f}",
            f"{100 * row['hold_share']:.0f}%",
        )
    return table
