"""SimplerEnv-like variant runs in SimplerEnv's terms: canonical ("visual matching")
success, variant-aggregated success, the drop per axis, and whether the variants rank
policies as the canonical scene does (MMRV, Kendall tau).

Aggregated success is the mean over the selected variants of each variant's success
rate (each variant counts once, as SimplerEnv averages its variants). Its interval is a
percentile bootstrap over layouts (a task's seed): every variant replays the same
layouts, so outcomes under different variants of one layout are not independent, and
resampling layouts, not episodes, keeps that. The seed is fixed, so the same rows
always print the same interval.

Ranking stability compares, for each variant, the policies' success under it with
their canonical success (the reference ranking, as SimplerEnv compares simulation with
real-world success):

    MMRV = 1/N sum_i max_j |R_i - R_j| * 1[(R_i < R_j) != (S_i < S_j)]

with R the canonical and S the variant success of N policies: the largest canonical gap
a variant inverts, averaged over policies (0 = same order; in success units). Kendall's
tau-b between R and S is given beside it (1 = same order). Both are averaged over the
variants, and per axis.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import pandas as pd

from results.render import Cell, finite_or_none
from results.summary import Success

CANONICAL = "canonical"
BOOTSTRAP_RESAMPLES = 10_000
BOOTSTRAP_SEED = 0


def axis_of(variant: str) -> str:
    return variant.split("=", 1)[0]


def is_variant_run(episodes: pd.DataFrame) -> bool:
    """Rows that ran under more than the canonical scene."""
    if "variant" not in episodes:
        return False
    seen = set(episodes["variant"].dropna())
    return bool(seen - {CANONICAL})


@dataclass(frozen=True)
class VariantStats:
    canonical: Success  # the canonical scene's episodes
    per_variant: dict[str, float]  # variant label -> success rate (canonical included)
    aggregated: float  # mean over the non-canonical variants
    aggregated_interval: tuple[float, float]

    def per_axis(self) -> dict[str, float]:
        """Mean success over each axis's levels, in the order the variants came."""
        axes: dict[str, list[float]] = {}
        for label, rate in self.per_variant.items():
            if label != CANONICAL:
                axes.setdefault(axis_of(label), []).append(rate)
        return {axis: float(np.mean(rates)) for axis, rates in axes.items()}

    def aggregated_text(self) -> str:
        if math.isnan(self.aggregated):
            return "-"
        low, high = self.aggregated_interval
        return f"{100 * self.aggregated:.1f}% [{100 * low:.0f}, {100 * high:.0f}]"

    def axis_text(self, axis: str) -> str:
        rate = self.per_axis().get(axis)
        if rate is None:
            return "-"
        return f"{100 * rate:.1f}% ({100 * (rate - self.canonical.rate):+.1f})"


def variant_stats(rows: pd.DataFrame) -> VariantStats:
    """One policy configuration's rows (any tasks): success per variant, and the
    aggregated mean with a bootstrap over (task, seed) layouts."""
    rows = rows[rows["variant"].notna()]
    success = rows["success"].astype(float)
    per_variant = {str(v): float(g.mean()) for v, g in success.groupby(rows["variant"], sort=False)}
    canonical = rows[rows["variant"] == CANONICAL]
    others = [v for v in per_variant if v != CANONICAL]
    aggregated = float(np.mean([per_variant[v] for v in others])) if others else math.nan
    interval = (math.nan, math.nan)
    if others:
        table = (
            rows[rows["variant"] != CANONICAL]
            .assign(layout=rows["task"].astype(str) + "#" + rows["seed"].astype(str), ok=success)
            .pivot_table(index="variant", columns="layout", values="ok", aggfunc="mean")
        )
        matrix = table.to_numpy(dtype=float)  # variants x layouts; NaN where a variant skipped one
        rng = np.random.default_rng(BOOTSTRAP_SEED)
        picks = rng.integers(0, matrix.shape[1], size=(BOOTSTRAP_RESAMPLES, matrix.shape[1]))
        with np.errstate(invalid="ignore"):
            means = np.nanmean(np.nanmean(matrix[:, picks], axis=2), axis=0)
        low, high = np.nanpercentile(means, [2.5, 97.5])
        interval = (float(low), float(high))
    return VariantStats(
        Success(int(canonical["success"].sum()), len(canonical)), per_variant, aggregated, interval
    )


# --- ranking stability ------------------------------------------------------------------


def mmrv(reference: np.ndarray, other: np.ndarray) -> float:
    """Mean maximum rank violation of `other` against `reference` (module docstring)."""
    r, s = np.asarray(reference, float), np.asarray(other, float)
    if len(r) < 2:
        return math.nan
    violated = (r[:, None] < r[None, :]) != (s[:, None] < s[None, :])
    return float(np.mean(np.max(np.abs(r[:, None] - r[None, :]) * violated, axis=1)))


def kendall_tau(a: np.ndarray, b: np.ndarray) -> float:
    """Kendall's tau-b (ties in either ranking handled); NaN when a ranking is all ties."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    i, j = np.triu_indices(len(a), k=1)
    da, db = np.sign(a[i] - a[j]), np.sign(b[i] - b[j])
    concordant_minus_discordant = float(np.sum(da * db))
    pairs_a, pairs_b = float(np.sum(da != 0)), float(np.sum(db != 0))
    if pairs_a == 0 or pairs_b == 0:
        return math.nan
    return concordant_minus_discordant / math.sqrt(pairs_a * pairs_b)


@dataclass(frozen=True)
class RankingStability:
    policies: int
    mmrv: float  # mean over the variants
    kendall_tau: float  # mean over the variants where it is defined
    per_axis: dict[str, tuple[float, float]]  # axis -> (mean MMRV, mean tau) over its levels

    def text(self) -> str:
        if self.policies < 2:
            return "ranking stability: n/a (one policy configuration; it needs two or more)"
        axes = "; ".join(f"{a} {m:.3f} / {_num(t)}" for a, (m, t) in self.per_axis.items())
        return (
            f"ranking stability vs canonical over {self.policies} policy configurations: MMRV "
            f"{self.mmrv:.3f} (0 = same order), Kendall tau {_num(self.kendall_tau)} (1 = same order); "
            f"per axis MMRV / tau: {axes}"
        )


def _num(value: float) -> str:
    return "-" if math.isnan(value) else f"{value:.2f}"


def ranking_stability(stats: Mapping[str, VariantStats]) -> RankingStability:
    """From each policy configuration's VariantStats (keyed by configuration)."""
    names = list(stats)
    variants = [v for v in next(iter(stats.values())).per_variant if v != CANONICAL] if stats else []
    variants = [v for v in variants if all(v in s.per_variant for s in stats.values())]
    reference = np.array([stats[n].canonical.rate for n in names])
    per_variant = {}
    for v in variants:
        other = np.array([stats[n].per_variant[v] for n in names])
        per_variant[v] = (mmrv(reference, other), kendall_tau(reference, other))
    per_axis: dict[str, list[tuple[float, float]]] = {}
    for v, pair in per_variant.items():
        per_axis.setdefault(axis_of(v), []).append(pair)

    def mean(values: list[float]) -> float:
        finite = [x for x in values if not math.isnan(x)]
        return float(np.mean(finite)) if finite else math.nan

    return RankingStability(
        len(names),
        mean([m for m, _ in per_variant.values()]),
        mean([t for _, t in per_variant.values()]),
        {a: (mean([m for m, _ in p]), mean([t for _, t in p])) for a, p in per_axis.items()},
    )


# --- cells for leaderboards (results/leaderboard.py) -------------------------------------


def variant_cells(stats: VariantStats | None, axes: tuple[str, ...]) -> list[Cell]:
    if stats is None:
        return [Cell("-", None)] * (2 + len(axes))
    per_axis = stats.per_axis()
    return [
        Cell(stats.canonical.text(), finite_or_none(stats.canonical.rate)),
        Cell(stats.aggregated_text(), finite_or_none(stats.aggregated)),
        *(Cell(stats.axis_text(a), finite_or_none(per_axis.get(a, math.nan))) for a in axes),
    ]


def variant_columns(stats: VariantStats) -> dict[str, float]:
    low, high = stats.canonical.interval
    agg_low, agg_high = stats.aggregated_interval
    out = {
        "canonical_success": stats.canonical.rate,
        "canonical_low": low,
        "canonical_high": high,
        "aggregated_success": stats.aggregated,
        "aggregated_low": agg_low,
        "aggregated_high": agg_high,
    }
    out |= {f"success[{a}]": rate for a, rate in stats.per_axis().items()}
    return out | {f"success[{v}]": rate for v, rate in stats.per_variant.items()}
