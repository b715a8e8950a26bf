"""Figures for ablations, the speed/success trade-off and decoding order, from tidy rows.

Pure functions: DataFrames in, a matplotlib `Figure` out, saved as PNG or SVG when
`out` is given (written to a temporary file and renamed, so a failure never leaves half
a figure). Figures are built with the object API on the Agg renderer: no pyplot state,
no display needed.

Any knob can be an axis without code: a column may be an episode-table column, a
policy parameter (parsed from `policy_params`) or a field of the checkpoint's header
(recipe, noise_schedule, block_size, ...: what training fixed). Prefixed names
(`param.steps`, `checkpoint.block_size`) are always available; the bare name works when
it is unambiguous (an episode column wins over a parameter, a parameter over a
checkpoint field). A decode `block_size` of 0 means "the checkpoint's" and is shown as
that block size.
"""

from __future__ import annotations

import json
import math
import os
import re
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from matplotlib import rc_context
from matplotlib.figure import Figure
from matplotlib.ticker import PercentFormatter

from results.labels import not_using, param_users, row_labels
from results.leaderboard import DEFAULT_BASELINE
from results.plot_speedup import SPEEDUP, baseline_configs, speedup_interval, with_speedup
from results.schema import COLUMNS
from results.summary import t_quantile, wilson_interval

SUFFIXES = (".png", ".svg")
PARAM, CKPT = "param.", "checkpoint."
# Axes where smaller is better; everything else (success, tokens/s, Hz) is larger-better.
LOWER_IS_BETTER = frozenset(
    {"nfe_per_chunk", "nfe_total", "wall_clock_s", "policy_time_s", "env_time_s", "overhead_s", "steps"}
)
_UNITS = {c.name: c.unit for c in COLUMNS}
_MARKERS = "osD^vP*Xhp<>"


class PlotInputError(ValueError):
    """A figure cannot be made from these inputs; the message names the valid choices."""


# ---------------------------------------------------------------------------- columns


def _checkpoint_fields_from_files(paths: Sequence[str]) -> dict[str, dict[str, Any]]:
    from policies.dvla.policy import checkpoint_fields  # torch-free header read

    return {p: checkpoint_fields(p) for p in paths if p}


def plot_frame(
    episodes: pd.DataFrame, checkpoints: Mapping[str, Mapping[str, Any]] | None = None
) -> pd.DataFrame:
    """`episodes` plus a column per policy parameter and per checkpoint-header field.

    `checkpoints` maps policy_config_id to header fields (as recorded in a run's
    manifest); configurations it lacks are looked up in the checkpoint file, if present.
    """
    if any(c.startswith(PARAM) for c in episodes.columns):
        return episodes  # already expanded
    df = episodes.copy()
    parsed = {s: json.loads(s) for s in df["policy_params"].unique()} if "policy_params" in df else {}
    for key in sorted({k for params in parsed.values() for k in params}):
        df[PARAM + key] = df["policy_params"].map(lambda s, k=key: parsed[s].get(k))
    known = dict(checkpoints or {})
    missing = df.loc[~df["policy_config_id"].isin(list(known)), ["policy_config_id", "checkpoint"]]
    missing = missing.drop_duplicates("policy_config_id")
    from_files = _checkpoint_fields_from_files(list(missing["checkpoint"].unique()))
    for config_id, path in missing.itertuples(index=False):
        known[config_id] = from_files.get(path, {})
    for field in sorted({f for fields in known.values() for f in fields}):
        df[CKPT + field] = df["policy_config_id"].map(lambda c, f=field: (known.get(c) or {}).get(f))
    if PARAM + "block_size" in df and CKPT + "block_size" in df:
        use_ckpt = (df[PARAM + "block_size"] == 0) & df[CKPT + "block_size"].notna()
        df[PARAM + "block_size"] = df[PARAM + "block_size"].where(~use_ckpt, df[CKPT + "block_size"])
    aliases: dict[str, str] = {}
    for prefixed in [c for c in df.columns if c.startswith((PARAM, CKPT))]:
        bare = prefixed.split(".", 1)[1]
        if bare not in df.columns:
            df[bare] = df[prefixed]
            aliases[bare] = prefixed
    df.attrs["aliases"] = aliases
    df["config_label"] = df["policy_config_id"].map(config_labels(df))
    return df


def config_labels(df: pd.DataFrame) -> dict[str, str]:
    """The configurations' labels as the rows hold them (results.labels): a legend names a
    configuration as every table does. A default block size (0, the checkpoint's) plots at
    the checkpoint's block size on an axis, but keeps its table name (`fast_dvla`)."""
    return row_labels(df)


def natural_key(text: str) -> list[Any]:
    """Sort key that puts block_size=4 before block_size=16."""
    return [
        (0, float(t), "") if re.fullmatch(r"\d+(\.\d+)?", t) else (1, 0.0, t)
        for t in re.split(r"(\d+(?:\.\d+)?)", text)
        if t
    ]


def _numeric(series: pd.Series) -> pd.Series | None:
    if series.dtype == bool:
        return series.astype(float)
    values = pd.to_numeric(series, errors="coerce")
    return values if values.notna().any() and values[series.notna()].notna().all() else None


def _resolve(df: pd.DataFrame, name: str, role: str, numeric: bool = False) -> str:
    if name in df.columns and (not numeric or _numeric(df[name]) is not None):
        return name
    hidden = {"config_label", "run_id", "policy_params", "started_at", "instruction", "failure_reason"}
    aliases = df.attrs.get("aliases", {})
    shown = {v: k for k, v in aliases.items()}  # a prefixed column by its bare name when it has one
    groups: dict[str, list[str]] = {"episode columns": [], "policy parameters": [], "checkpoint fields": []}
    for c in df.columns:
        if c in hidden or c in aliases or (numeric and _numeric(df[c].dropna()) is None):
            continue
        group = (
            "policy parameters"
            if c.startswith(PARAM)
            else "checkpoint fields"
            if c.startswith(CKPT)
            else "episode columns"
        )
        groups[group].append(shown.get(c, c))
    listed = "; ".join(f"{g}: {', '.join(names)}" for g, names in groups.items() if names)
    what = "numeric " if numeric else ""
    raise PlotInputError(f"no {what}column {name!r} for {role}; valid choices are {listed}")


def _axis_label(name: str, baseline: str | None = None) -> str:
    unit = _UNITS.get(name, "")
    if name == "success":
        return "success rate"
    if name == SPEEDUP:
        return f"speedup over {baseline} (x)"
    return f"{name} ({unit})" if unit and unit not in ("JSON", "path", "UTC") else name


# ---------------------------------------------------------------------------- statistics


def interval(values: pd.Series, is_success: bool) -> tuple[float, float, float, int]:
    """(estimate, low, high, n): Wilson for success, a t interval of the mean otherwise."""
    values = values.dropna().astype(float)
    n = len(values)
    if n == 0:
        return (math.nan, math.nan, math.nan, 0)
    if is_success:
        low, high = wilson_interval(int(values.sum()), n)
        rate = float(values.mean())  # inside its interval despite rounding (error bars >= 0)
        return (rate, min(low, rate), max(high, rate), n)
    mean = float(values.mean())
    if n == 1:
        return (mean, math.nan, math.nan, 1)  # one episode: no interval, not a zero-width one
    half = t_quantile(n - 1) * float(values.std(ddof=1)) / math.sqrt(n)
    floor = 0.0 if values.min() >= 0 else -math.inf  # a rate's interval stays >= 0
    return (mean, max(mean - half, floor), mean + half, n)


def measure(rows: pd.DataFrame, col: str) -> tuple[float, float, float, int]:
    """A column's estimate and 95% interval over rows: speedup as results/plot_speedup.py
    defines it (a ratio of means over paired episodes), success as Wilson, else a t mean."""
    if col == SPEEDUP:
        return speedup_interval(rows)
    return interval(_numeric(rows[col]), col == "success")


def _with_speedup(df: pd.DataFrame, columns: Sequence[str | None], baseline: str | None) -> pd.DataFrame:
    if SPEEDUP not in columns:
        return df
    try:
        return with_speedup(df, baseline or "")
    except ValueError as exc:
        raise PlotInputError(str(exc)) from None


# ---------------------------------------------------------------------------- output


def check_out(out: str | os.PathLike[str] | None) -> Path | None:
    if out is None:
        return None
    path = Path(out)
    if path.suffix.lower() not in SUFFIXES:
        raise PlotInputError(
            f"{str(path)!r}: cannot write a {path.suffix or 'suffix-less'} figure; use one of {', '.join(SUFFIXES)}"
        )
    return path


def _save(fig: Figure, out: str | os.PathLike[str] | None) -> None:
    path = check_out(out)
    if path is None:
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    fmt = path.suffix.lower()[1:]
    try:
        metadata = {"Date": None} if fmt == "svg" else None  # same rows, same bytes
        with rc_context({"svg.hashsalt": "dvla-harness"}):
            fig.savefig(tmp, format=fmt, dpi=150, bbox_inches="tight", metadata=metadata)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def _colors(n: int) -> list[Any]:
    from matplotlib import colormaps

    cmap = colormaps["tab10" if n <= 10 else "tab20"]
    return [cmap(i % cmap.N) for i in range(n)]


# ---------------------------------------------------------------------------- figures


def _x_positions(values: pd.Series) -> tuple[dict[Any, float], bool, list[Any]]:
    """Where each x value goes, whether the axis is log2, and the values in order."""
    numeric = _numeric(values)
    if numeric is not None:
        order = sorted(numeric.dropna().unique())
        log = len(order) > 2 and order[0] > 0 and order[-1] / order[0] >= 4  # block sizes double
        return {v: float(v) for v in order}, log, order
    order = sorted(set(values.dropna().astype(str)), key=natural_key)
    return {v: float(i) for i, v in enumerate(order)}, False, order


def ablation_plot(
    episodes: pd.DataFrame,
    x: str,
    y: list[str],
    hue: str | None = None,
    out: str | os.PathLike[str] | None = None,
    baseline: str | None = DEFAULT_BASELINE,
) -> Figure:
    """One panel per y column against x, a line per hue value, with 95% intervals
    (Wilson for success, t for means of rates, the ratio estimator's for speedup). The
    baseline's configuration, when it has no x (a sweep's `--reference bidirectional`
    beside a block-size grid), is a horizontal line with its interval as a band."""
    check_out(out)
    if not y:
        raise PlotInputError("no y column given; e.g. success,tokens_per_s")
    df = _with_speedup(plot_frame(episodes), y, baseline)
    x = _resolve(df, x, "x")
    ys = [_resolve(df, c, "y", numeric=True) for c in y]
    hue = _resolve(df, hue, "hue") if hue else None
    whole = df
    df = _configurations_using(df, x, baseline_configs(df, baseline))
    lines = whole[whole["policy_config_id"].isin(baseline_configs(whole, baseline))]
    lines = lines[~lines["policy_config_id"].isin(df["policy_config_id"])]
    _check_not_pooled(df, hue)
    numeric_x = _numeric(df[x]) is not None
    xkey = _numeric(df[x]) if numeric_x else df[x].astype(str)
    df = df.assign(_x=xkey)
    positions, log, order = _x_positions(df[x])
    groups = [(None, df)] if hue is None else list(df.groupby(df[hue].map(_fmt), sort=False))
    groups.sort(key=lambda g: natural_key(str(g[0])))
    colors = _colors(len(groups))
    fig = Figure(figsize=(4.3 * len(ys) + (1.6 if hue else 0), 3.6), layout="constrained")
    axes = fig.subplots(1, len(ys), squeeze=False)[0]
    counts: list[int] = []
    step = min(np.diff(sorted(positions.values())), default=1.0) if not log else 1.0
    for ax, col in zip(axes, ys, strict=True):
        is_success = col == "success"
        for i, (name, part) in enumerate(groups):
            spread = (0.15 if not numeric_x else 0.06) * min(1.0, 4 / len(groups))
            dodge = (i - (len(groups) - 1) / 2) * spread  # side by side, bars not on top of each other
            px, est, low, high = [], [], [], []
            for value in order:
                cell = part[part["_x"] == value]
                if cell.empty:
                    continue
                e, lo, hi, n = measure(cell, col)
                if n == 0:
                    continue
                counts.append(n)
                pos = positions[value]
                px.append(pos * 2**dodge if log else pos + dodge * step)
                est.append(e)
                low.append(e - lo)
                high.append(hi - e)
            if not px:
                continue
            ax.errorbar(
                px,
                est,
                yerr=[low, high],
                marker=_MARKERS[i % len(_MARKERS)],
                color=colors[i],
                capsize=3,
                linewidth=1.6,
                linestyle="-" if numeric_x else "none",  # no line through unordered categories
                markersize=6,
                label=str(name) if name is not None else None,
            )
        _baseline_lines(ax, lines, col)
        if log:
            ax.set_xscale("log", base=2)
        ax.set_xticks([positions[v] for v in order], [_fmt(v) for v in order])
        ax.minorticks_off()
        ax.set_xlabel(_axis_label(x))
        ax.set_ylabel(_axis_label(col, baseline))
        ax.grid(alpha=0.3)
        if is_success:
            ax.yaxis.set_major_formatter(PercentFormatter(1.0))
            ax.set_ylim(-0.03, 1.03)
    n_text = (
        f"{min(counts)}"
        if counts and min(counts) == max(counts)
        else f"{min(counts, default=0)}-{max(counts, default=0)}"
    )
    speed = f"; speedup: tokens/s over {baseline}'s, paired episodes" if SPEEDUP in ys else ""
    fig.suptitle(
        f"{', '.join(ys)} vs {x}: mean and 95% interval (Wilson for success, t for means); "
        f"{n_text} episodes per point{speed}",
        fontsize=9,
    )
    handles, labels = axes[0].get_legend_handles_labels()
    if labels:
        fig.legend(
            handles,
            labels,
            title=hue,
            loc="outside lower center",
            ncols=min(len(labels), 6),
            fontsize=8,
            title_fontsize=9,
        )
    _save(fig, out)
    return fig


def _baseline_lines(ax: Any, rows: pd.DataFrame, col: str) -> None:
    """The baseline configuration as a dashed line at its mean (a band: its interval)."""
    for _, part in rows.groupby("policy_config_id", sort=False):
        est, low, high, n = measure(part, col)
        if n == 0:
            continue
        label = f"{part['config_label'].iloc[0]} (baseline, n={n})"
        ax.axhline(est, color="0.25", linestyle="--", linewidth=1.2, label=label, zorder=1)
        if np.isfinite(low) and np.isfinite(high) and high > low:
            ax.axhspan(low, high, color="0.25", alpha=0.12, linewidth=0, zorder=0)


def _configurations_using(df: pd.DataFrame, x: str, baselines: Sequence[str] = ()) -> pd.DataFrame:
    """The rows of configurations that use the x parameter (fast_dllm's block_size of 0 is
    no block size: a point at x=0 no decoder ran); the others named in one warning, but
    for the baseline's, which the figure draws as a line."""
    key = x if x.startswith(PARAM) else df.attrs.get("aliases", {}).get(x, "")
    dropped = not_using(df, key[len(PARAM) :]) if key.startswith(PARAM) else {}
    names = ", ".join(v for k, v in dropped.items() if k not in baselines)
    if dropped and len(dropped) == df["policy_config_id"].nunique():
        users = ", ".join(param_users(key[len(PARAM) :])) or "none registered"
        raise PlotInputError(f"no configuration in these rows uses {x} ({names}); valid users: {users}")
    if names:
        warnings.warn(f"left out of the plot, as they do not use {x}: {names}", UserWarning, stacklevel=3)
    return df[~df["policy_config_id"].isin(list(dropped))]


def _check_not_pooled(df: pd.DataFrame, hue: str | None) -> None:
    """One point per x value per line: rows of two policies at one x (fast_dvla and
    block_diffusion at block size 4) are different decoders, and pooling them into one
    rate would show neither. A hue must keep the policies apart."""
    policies = list(dict.fromkeys(df["policy"]))
    if len(policies) < 2:
        return
    if hue is not None and (df.groupby(df[hue].map(_fmt), sort=False)["policy"].nunique() == 1).all():
        return
    why = "no --hue" if hue is None else f"--hue {hue} has values shared by several policies"
    raise PlotInputError(
        f"these rows hold {len(policies)} policies ({', '.join(map(str, policies))}) and {why}: "
        "each point would pool different decoders; pass --hue policy or --hue config_label, "
        "or plot runs of one policy"
    )


def _fmt(value: Any) -> str:
    if isinstance(value, float) and value.is_integer():
        return str(int(value))
    return f"{value:g}" if isinstance(value, float) else str(value)


def _frontier(xs: np.ndarray, ys: np.ndarray, x_up: bool, y_up: bool) -> list[int]:
    """Indices of configurations no other one beats on both axes, in x order."""
    sx, sy = (xs if x_up else -xs), (ys if y_up else -ys)
    keep = []
    for i in range(len(xs)):
        dominated = any(
            sx[j] >= sx[i] and sy[j] >= sy[i] and (sx[j] > sx[i] or sy[j] > sy[i])
            for j in range(len(xs))
            if j != i
        )
        if not dominated and not (math.isnan(sx[i]) or math.isnan(sy[i])):
            keep.append(i)
    return sorted(keep, key=lambda i: xs[i])


def pareto_plot(
    episodes: pd.DataFrame,
    x: str = "tokens_per_s",
    y: str = "success",
    out: str | os.PathLike[str] | None = None,
    baseline: str | None = DEFAULT_BASELINE,
) -> Figure:
    """Speed against success, one marker per policy configuration with its 95% intervals,
    and the frontier of configurations that no other beats on both; `speedup` on an axis
    is over the baseline run beside them (results/plot_speedup.py)."""
    check_out(out)
    df = _with_speedup(plot_frame(episodes), (x, y), baseline)
    x = _resolve(df, x, "x", numeric=True)
    y = _resolve(df, y, "y", numeric=True)
    # Configurations with no value on an axis (tokens/s of a policy that decodes no tokens:
    # scripted, random) have no place on the plot; none at all means another axis.
    measured = df.groupby("policy_config_id")[[x, y]].apply(lambda g: g.notna().any().all())
    if not measured.any():
        raise PlotInputError(
            f"no configuration has values for both {x} and {y} (policies that decode no tokens have "
            "no tokens_per_s); pass another axis, e.g. --x control_hz or --x wall_clock_s"
        )
    df = df[df["policy_config_id"].isin(measured[measured].index)]
    points = []
    for _, part in df.groupby("policy_config_id", sort=False):
        ex, ey = measure(part, x), measure(part, y)
        points.append((part["config_label"].iloc[0], ex, ey, len(part)))
    points.sort(key=lambda p: natural_key(p[0]))
    xs = np.array([p[1][0] for p in points], dtype=float)
    ys = np.array([p[2][0] for p in points], dtype=float)
    x_up, y_up = x not in LOWER_IS_BETTER, y not in LOWER_IS_BETTER
    front = _frontier(xs, ys, x_up, y_up)
    fig = Figure(figsize=(7.2, 4.2), layout="constrained")
    ax = fig.subplots()
    if len(front) > 1:
        ax.plot(
            xs[front], ys[front], "--", color="0.45", linewidth=1.2, zorder=1, label="Pareto frontier (*)"
        )
    colors = _colors(len(points))
    for i, (label, ex, ey, n) in enumerate(points):
        ax.errorbar(
            ex[0],
            ey[0],
            xerr=[[ex[0] - ex[1]], [ex[2] - ex[0]]],
            yerr=[[ey[0] - ey[1]], [ey[2] - ey[0]]],
            marker=_MARKERS[i % len(_MARKERS)],
            markersize=8 if i in front else 6,
            markeredgecolor="black" if i in front else colors[i],
            color=colors[i],
            ecolor=(*colors[i][:3], 0.45),  # light bars: the markers are what to read
            elinewidth=1.2,
            capsize=3,
            linestyle="none",
            zorder=2,
            label=f"{label} (n={n})" + (" *" if i in front else ""),
        )
    for axis, col in (("x", x), ("y", y)):
        direction = "lower is better" if col in LOWER_IS_BETTER else "higher is better"
        getattr(ax, f"set_{axis}label")(f"{_axis_label(col, baseline)}, {direction}")
        if col == "success":
            getattr(ax, f"{axis}axis").set_major_formatter(PercentFormatter(1.0))
            getattr(ax, f"set_{axis}lim")(-0.03, 1.03)
    ax.grid(alpha=0.3)
    ax.set_title(f"{y} vs {x}, 95% intervals", fontsize=10)
    ncols = 1 if len(points) <= 4 else 2  # below the axes: long labels never squeeze the plot
    fig.legend(loc="outside lower center", ncols=ncols, fontsize=8)
    _save(fig, out)
    return fig
