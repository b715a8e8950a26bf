"""The decoding-order figure: which action position each forward pass of a chunk commits,
from a run's decode traces (`--traces`, docs/sweeps-and-plots.md)."""

from __future__ import annotations

import math
import os

import numpy as np
import pandas as pd
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator

from results.plots import PlotInputError, _save, check_out, natural_key


def decoding_order_plot(traces: pd.DataFrame, out: str | os.PathLike[str] | None = None) -> Figure:
    """Per configuration, how often each action position is committed at each forward
    pass of a chunk; white dots mark each position's mean pass, thin lines the block
    boundaries (left-to-right, block-wise decoding is a descending staircase)."""
    check_out(out)
    if traces is None or traces.empty or "committed" not in traces:
        raise PlotInputError("no decode traces to plot (record them with `--traces` on run or sweep)")
    if "config_label" not in traces:
        traces = traces.assign(config_label=traces.get("policy_config_id", pd.Series("all", traces.index)))
    panels = sorted(traces.groupby("config_label", sort=False), key=lambda p: natural_key(str(p[0])))
    width = 1 + max(p for passes in traces["committed"] for step in passes for p in step)
    cols = min(3, len(panels))
    rows = math.ceil(len(panels) / cols)
    fig = Figure(figsize=(4.2 * cols + 1.0, 3.3 * rows), layout="constrained")
    axes = np.atleast_1d(fig.subplots(rows, cols, squeeze=False)).ravel()
    image = None
    for ax, (label, part) in zip(axes, panels, strict=False):
        depth = max(len(passes) for passes in part["committed"])
        counts = np.zeros((depth, width))
        for passes in part["committed"]:
            for step, positions in enumerate(passes):
                counts[step, positions] += 1
        freq = counts / len(part)
        image = ax.imshow(
            freq, aspect="auto", cmap="viridis", vmin=0, vmax=1, origin="upper", interpolation="nearest",
            extent=(-0.5, width - 0.5, depth + 0.5, 0.5),
        )  # fmt: skip
        with np.errstate(invalid="ignore"):
            mean_pass = (counts * np.arange(1, depth + 1)[:, None]).sum(0) / counts.sum(0)
        ax.plot(np.arange(width), mean_pass, "o", color="white", markersize=2.5, markeredgecolor="black",
                markeredgewidth=0.3)  # fmt: skip
        block = part["block_size"].iloc[0] if "block_size" in part else None
        if block and not pd.isna(block) and 0 < int(block) < width:
            for edge in range(int(block), width, int(block)):
                ax.axvline(edge - 0.5, color="white", linewidth=0.5, alpha=0.6)
        nfe = np.mean([len(p) for p in part["committed"]])
        ax.set_title(f"{label}\n{len(part)} chunks, {nfe:.1f} passes/chunk", fontsize=9)
        ax.set_xlabel("action token position")
        ax.set_ylabel("forward pass")
        ax.yaxis.set_major_locator(MaxNLocator(integer=True))
    for ax in axes[len(panels) :]:
        ax.set_visible(False)
    if image is not None:
        fig.colorbar(
            image, ax=list(axes[: len(panels)]), label="fraction of chunks committing it", shrink=0.9
        )
    _save(fig, out)
    return fig
