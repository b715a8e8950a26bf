"""Speedup in plots: a configuration's tokens/s over a baseline's, the baseline run beside
it in the same run (a sweep's `--reference`), paired episode by episode.

Pairs are rows of one run with the same task and episode index, so both were timed
under the same machine load, interleaved; rows of other runs never pair (they may come
from another machine). The estimate is the ratio of the mean tokens/s over the pairs,
the leaderboard's speedup on an interleaved run; its 95% interval is the ratio
estimator's (Cochran, Sampling Techniques, 1977, section 6.4): with d_i = a_i - R b_i,
var(R) ~ var(d) / (n mean(b)^2), and a Student t quantile on n - 1 degrees of freedom,
so the interval narrows when the pairs move together, as interleaved timings do.
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd

from results.summary import t_quantile

SPEEDUP = "speedup"
BASELINE_TOKENS = "_baseline_tokens_per_s"
PAIR = ["run", "task", "episode_index"]


def baseline_configs(df: pd.DataFrame, baseline: str | None) -> list[str]:
    """The baseline's configuration ids (by policy name or id), in the order they ran."""
    if not baseline:
        return []
    mine = (df["policy"] == baseline) | (df["policy_config_id"] == baseline)
    return list(dict.fromkeys(df.loc[mine, "policy_config_id"]))


def with_speedup(df: pd.DataFrame, baseline: str) -> pd.DataFrame:
    """`df` with each row's paired baseline tokens/s and its `speedup` over it (NaN for a
    row with no pair). Raises ValueError naming the fix when there is nothing to pair with."""
    ids = baseline_configs(df, baseline)
    if not ids:
        raise ValueError(
            f"speedup needs {baseline} rows run beside the others, episode by episode: run the sweep "
            f"with --reference {baseline}, or name the baseline with --baseline POLICY"
        )
    if len(ids) > 1:
        raise ValueError(
            f"{baseline} has {len(ids)} configurations in these rows ({', '.join(ids)}); "
            "name one with --baseline CONFIG_ID"
        )
    pair = [c for c in PAIR if c in df]  # a bare episodes frame is one run
    base = df[df["policy_config_id"] == ids[0]].groupby(pair)["tokens_per_s"].mean().rename(BASELINE_TOKENS)
    out = df.drop(columns=[BASELINE_TOKENS, SPEEDUP], errors="ignore").join(base, on=pair)
    out[SPEEDUP] = pd.to_numeric(out["tokens_per_s"], errors="coerce") / out[BASELINE_TOKENS]
    out.attrs = dict(df.attrs)  # the plot frame's column aliases (results.plots.plot_frame)
    return out


def speedup_interval(rows: pd.DataFrame) -> tuple[float, float, float, int]:
    """(estimate, low, high, n) over the rows that have a pair (see the module docstring)."""
    both = rows[["tokens_per_s", BASELINE_TOKENS]].apply(pd.to_numeric, errors="coerce").dropna()
    both = both[both[BASELINE_TOKENS] > 0]
    n = len(both)
    if n == 0:
        return (math.nan, math.nan, math.nan, 0)
    a, b = both["tokens_per_s"].to_numpy(float), both[BASELINE_TOKENS].to_numpy(float)
    ratio = float(a.mean() / b.mean())
    if n == 1:
        return (ratio, math.nan, math.nan, 1)
    half = t_quantile(n - 1) * float(np.std(a - ratio * b, ddof=1)) / (math.sqrt(n) * float(b.mean()))
    return (ratio, max(ratio - half, 0.0), ratio + half, n)
