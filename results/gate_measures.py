"""The measures the CI gate compares (results/gate.py), read from a configuration pair's
episodes side by side: one row per episode both runs hold, each measure suffixed _b
(baseline) and _c (candidate). Per side: NFE and counted work per chunk (totals over
totals, so long episodes weigh what they decoded) and tokens/s over policy time.
"""

from __future__ import annotations

import pandas as pd

from results.pairing import PAIR_KEY, ConfigPair, episode_keys

MEASURES = (
    "success",
    "nfe_total",
    "flops_total",
    "chunks",
    "action_tokens_total",
    "policy_time_s",
    "task_index",
    "subtasks_completed",
)


def side_measures(merged: pd.DataFrame, side: str) -> pd.DataFrame:
    """One run's measures from a merged pair table (`side` is "b" or "c")."""
    return merged[[f"{m}_{side}" for m in MEASURES]].set_axis(list(MEASURES), axis=1)


def nfe_per_chunk(df: pd.DataFrame) -> float | None:
    if df["nfe_total"].isna().all():  # a remote server that reports none: not measured
        return None
    chunks = int(df["chunks"].sum())
    return float(df["nfe_total"].sum()) / chunks if chunks else None


def work_per_chunk(df: pd.DataFrame) -> float | None:
    """Counted FLOPs per chunk; None unless every row measured them (a sum with holes
    would read as a drop)."""
    if df.empty or df["flops_total"].isna().any():
        return None
    chunks = int(df["chunks"].sum())
    return float(df["flops_total"].astype(float).sum()) / chunks if chunks else None


def tokens_per_s(df: pd.DataFrame) -> float | None:
    decoded = df[df["action_tokens_total"] > 0]
    time_s = float(decoded["policy_time_s"].sum())
    return float(decoded["action_tokens_total"].sum()) / time_s if len(decoded) and time_s > 0 else None


def merged_pair(baseline: pd.DataFrame, candidate: pd.DataFrame, pair: ConfigPair) -> pd.DataFrame:
    """The pair's episodes side by side (measures suffixed _b and _c)."""
    b = episode_keys(baseline[baseline["policy_config_id"] == pair.baseline_id])
    c = episode_keys(candidate[candidate["policy_config_id"] == pair.candidate_id])
    b, c = (df if "subtasks_completed" in df else df.assign(subtasks_completed=None) for df in (b, c))
    b, c = (df if "flops_total" in df else df.assign(flops_total=None) for df in (b, c))
    cols = [*PAIR_KEY, *MEASURES]
    return b[cols].merge(c[cols], on=list(PAIR_KEY), suffixes=("_b", "_c"))


def work_unmeasured(merged: pd.DataFrame) -> str | None:
    """Which side left a pair's counted work unmeasured ('baseline', 'candidate', 'baseline
    and candidate'), or None when both measured it."""
    sides = [
        name
        for name, s in (("baseline", "b"), ("candidate", "c"))
        if work_per_chunk(side_measures(merged, s)) is None
    ]
    return " and ".join(sides) or None
