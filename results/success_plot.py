"""Success per task and configuration, with Wilson 95% intervals: the figure for suites
whose policies decode no tokens (a plugin's reach task, scripted experts), where a
speed-against-success Pareto plot has no axis to stand on."""

from __future__ import annotations

import pandas as pd
from matplotlib.figure import Figure
from matplotlib.ticker import PercentFormatter

from results.labels import config_labels
from results.plots import _colors
from results.summary import wilson_interval

MAX_TASKS = 20  # more tasks than this (MT50, LIBERO-90) and the figure shows the overall rate only


def success_plot(episodes: pd.DataFrame, title: str = "") -> Figure:
    """One marker per (task, configuration) with its interval, configurations side by
    side within each task; an `overall` group last. Labels are the tables' names."""
    labels = config_labels(episodes)
    configs = list(dict.fromkeys(episodes["policy_config_id"]))
    order = episodes.sort_values("task_index", kind="stable")["task"].drop_duplicates().tolist()
    tasks = [*order, "overall"] if 1 < len(order) <= MAX_TASKS else ["overall"]
    width = 0.8 / len(configs)
    fig = Figure(
        figsize=(max(4.5, 0.9 * len(tasks) * max(1, len(configs) / 2) + 2.5), 3.6), layout="constrained"
    )
    ax = fig.subplots()
    for c, (cid, color) in enumerate(zip(configs, _colors(len(configs)), strict=True)):
        mine = episodes[episodes["policy_config_id"] == cid]
        xs, ys, lows, highs = [], [], [], []
        for t, task in enumerate(tasks):
            rows = mine if task == "overall" else mine[mine["task"] == task]
            if rows.empty:
                continue
            k, n = int(rows["success"].sum()), len(rows)
            low, high = wilson_interval(k, n)
            xs.append(t - 0.4 + width * (c + 0.5))
            ys.append(k / n)
            lows.append(k / n - low)
            highs.append(high - k / n)
        ax.errorbar(xs, ys, yerr=[lows, highs], fmt="o", color=color, capsize=3, label=labels[cid])
    ax.set_xticks(
        range(len(tasks)),
        tasks,
        rotation=30 if len(tasks) > 4 else 0,
        ha="right" if len(tasks) > 4 else "center",
    )
    ax.set_ylim(-0.03, 1.03)
    ax.yaxis.set_major_formatter(PercentFormatter(1.0))
    ax.set_ylabel("success rate (Wilson 95%)")
    ax.grid(axis="y", alpha=0.3)
    ax.legend(fontsize="small", loc="best")
    if title:
        ax.set_title(title)
    return fig
