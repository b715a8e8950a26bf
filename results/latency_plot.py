"""`plot latency`: success against inference latency, a line per decoder and execution
(docs/latency.md). Built on the ablation plot: x is the recorded mode (`none`,
`passes:2`, `passes:4` ...; ordered naturally), a line per configuration and
execution, Wilson 95% intervals for success."""

from __future__ import annotations

import os

import pandas as pd
from matplotlib.figure import Figure

from results.plots import PlotInputError, ablation_plot

LINE = "decoder, execution"


def latency_frame(episodes: pd.DataFrame) -> pd.DataFrame:
    """Episodes with `latency` (the mode; `none` for rows before it was recorded) and a
    line label per configuration and execution; `none` rows join every execution's line,
    as its d = 0 point."""
    if "inference_latency" not in episodes or (episodes["inference_latency"].fillna("none") == "none").all():
        raise PlotInputError(
            "no run at an inference latency other than none; make some with "
            "`dvla-harness run ... --inference-latency passes:MS --execution sync|async`"
        )
    df = episodes.copy()
    df["latency"] = df["inference_latency"].fillna("none")
    df["execution"] = df["execution"].fillna("sync")
    label = df["config_label"] if "config_label" in df else df["policy"]
    executions = sorted(set(df.loc[df["latency"] != "none", "execution"]))
    at = df[df["latency"] != "none"].assign(**{LINE: label + ", " + df["execution"]})
    base = df[df["latency"] == "none"]
    zero = [base.assign(**{LINE: label[base.index] + ", " + e}) for e in executions]
    return pd.concat([at, *zero], ignore_index=True)


def latency_plot(episodes: pd.DataFrame, y: list[str], out: str | os.PathLike[str] | None = None) -> Figure:
    return ablation_plot(latency_frame(episodes), "latency", y, LINE, out=out)
