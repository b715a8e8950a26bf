"""SimplerEnv-like variant runs in SimplerEnv's terms: success in the canonical scene,
variant-aggregated success, the drop per axis, and whether the variants rank policies as
the canonical scene does (MMRV, Pearson r, Kendall tau).

The canonical scene is ManiSkill3's own default scene. It is not SimplerEnv's "visual
matching" (real images overlaid on the simulator, robot colourings averaged), which needs
real-world footage this harness does not have; it only plays that role as the reference.

Aggregated success is SimplerEnv's variant aggregation: the mean, each setting counted
once, over the canonical (base) scene and the variants of SimplerEnv's axes
(SIMPLERENV_AXES: backgrounds, lighting, distractors, table textures). Camera poses and
the physical axes (friction, mass) are the harness's own robustness axes: SimplerEnv
leaves camera out of its aggregate and has no physical variants, so they are reported per
axis only, never averaged in. The interval is a percentile bootstrap over layouts (a
task's seed): every variant replays the same layouts, so outcomes under different
variants of one layout are not independent, and resampling layouts, not episodes, keeps
that. The seed is fixed, so the same rows always print the same interval.

Ranking stability compares, for each variant, the policies' success under it (S) with
their canonical success (R, the reference, in the role SimplerEnv gives real-world
success), with SimplerEnv's own definitions (simpler_env/utils/metrics.py):

    MMRV = 1/N sum_i max_j |R_i - R_j| * 1[(S_i > S_j) != (R_i > R_j)]

the largest canonical gap a variant inverts, averaged over policies (0 = same order; in
success units). Strict `>` on both sides: a pair tied under one and ordered under the
other counts as a violation. Pearson's r is computed on the centred vectors, as
SimplerEnv does: 1 when they are equal after centring (so two constant vectors give 1),
else sum(r s) / (sqrt(sum r^2 sum s^2) + 1e-8), so a constant vector against a varying
one gives 0. Kendall's tau-b is given beside them (1 = same order). All three are averaged
over the variants, and per axis.
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
# SimplerEnv's variant aggregation (tools/calc_metrics_evaluation_videos.py): base scene,
# backgrounds, lighting, distractors, table textures; camera is left out ("only when
# investigating the effect of different robustness factors"), and it has no physical axes.
SIMPLERENV_AXES = ("background", "lighting", "distractors", "table")
HARNESS_AXES = ("camera", "friction", "mass")  # the harness's own robustness axes
BOOTSTRAP_RESAMPLES = 10_000
BOOTSTRAP_SEED = 0


def axis_of(variant: str) -> str:
    return variant.split("=", 1)[0]


def in_aggregate(variant: str) -> bool:
    """Whether a setting counts in SimplerEnv's variant aggregation (the canonical scene does)."""
    return variant == CANONICAL or axis_of(variant) in SIMPLERENV_AXES


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
    aggregated: float  # mean over the canonical scene and SimplerEnv's axes' variants
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
    """One policy configuration's rows (any tasks): success per variant, and SimplerEnv's
    aggregated mean with a bootstrap over (task, seed) layouts. NaN when the run selected
    no variant of SimplerEnv's axes: the canonical scene alone is not an aggregate."""
    rows = rows[rows["variant"].notna()]
    success = rows["success"].astype(float)
    per_variant = {str(v): float(g.mean()) for v, g in success.groupby(rows["variant"], sort=False)}
    canonical = rows[rows["variant"] == CANONICAL]
    counted = [v for v in per_variant if in_aggregate(v)]
    if not any(v != CANONICAL for v in counted):
        counted = []
    aggregated = float(np.mean([per_variant[v] for v in counted])) if counted else math.nan
    interval = (math.nan, math.nan)
    if counted:
        table = (
            rows[rows["variant"].isin(counted)]
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
    """Mean maximum rank violation of `other` (a variant) against `reference` (the
    canonical scene, SimplerEnv's real-world side): the gap is the reference's, and a
    pair is violated when strict `>` disagrees, ties included (module docstring)."""
    r, s = np.asarray(reference, float), np.asarray(other, float)
    if r.shape != s.shape:
        raise ValueError(f"mmrv: {len(r)} reference rates against {len(s)} others")
    if len(r) < 2:
        return math.nan
    violated = (s[:, None] > s[None, :]) != (r[:, None] > r[None, :])
    return float(np.mean(np.max(np.abs(r[:, None] - r[None, :]) * violated, axis=1)))


def pearson_r(reference: np.ndarray, other: np.ndarray) -> float:
    """Pearson's r with SimplerEnv's conventions, so that tied policies (state policies
    score alike under every visual axis) print what SimplerEnv would: 1 when the centred
    vectors are equal (two constant ones too), 0 for a constant against a varying one."""
    r, s = np.asarray(reference, float), np.asarray(other, float)
    if r.shape != s.shape:
        raise ValueError(f"pearson_r: {len(r)} reference rates against {len(s)} others")
    if len(r) < 2:
        return math.nan
    r, s = r - r.mean(), s - s.mean()
    if np.all(r == s):
        return 1.0
    return float(np.sum(r * s) / (math.sqrt(float(np.sum(r**2) * np.sum(s**2))) + 1e-8))


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
    """The headline numbers are means over the variants of SimplerEnv's axes only;
    the harness's own axes (camera, physical) appear per axis, labelled apart."""

    policies: int
    mmrv: float  # mean over the variants of SimplerEnv's axes
    pearson: float  # likewise
    kendall_tau: float  # likewise, where it is defined
    per_axis: dict[str, tuple[float, float, float]]  # axis -> mean (MMRV, Pearson r, tau) over its levels

    def text(self) -> str:
        if self.policies < 2:
            return "ranking stability: n/a (one policy configuration; it needs two or more)"

        def axes(names: list[str]) -> str:
            return "; ".join(
                f"{a} {_num(m, 3)} / {_num(p)} / {_num(t)}"
                for a, (m, p, t) in self.per_axis.items()
                if a in names
            )

        ours = [a for a in self.per_axis if a not in SIMPLERENV_AXES]
        text = (
            f"ranking stability vs the canonical scene over {self.policies} policy configurations, "
            f"SimplerEnv's axes: MMRV {_num(self.mmrv, 3)} (0 = same order), Pearson r "
            f"{_num(self.pearson)}, Kendall tau {_num(self.kendall_tau)} (1 = same order); "
            f"per axis MMRV / Pearson r / tau: {axes(list(SIMPLERENV_AXES)) or 'none run'}"
        )
        if ours:
            text += f"; the harness's own axes, not in SimplerEnv's aggregate: {axes(ours)}"
        return text


def _num(value: float, decimals: int = 2) -> str:
    return "-" if math.isnan(value) else f"{value:.{decimals}f}"


def ranking_stability(stats: Mapping[str, VariantStats]) -> RankingStability:
    """From each policy configuration's VariantStats (keyed by configuration)."""
    names = list(stats)
    variants = [v for v in next(iter(stats.values())).per_variant if v != CANONICAL] if stats else []
    variants = [v for v in variants if all(v in s.per_variant for s in stats.values())]
    reference = np.array([stats[n].canonical.rate for n in names])
    per_variant = {}
    for v in variants:
        other = np.array([stats[n].per_variant[v] for n in names])
        per_variant[v] = (mmrv(reference, other), pearson_r(reference, other), kendall_tau(reference, other))
    per_axis: dict[str, list[tuple[float, float, float]]] = {}
    for v, pair in per_variant.items():
        per_axis.setdefault(axis_of(v), []).append(pair)

    def mean(values: list[float]) -> float:
        finite = [x for x in values if not math.isnan(x)]
        return float(np.mean(finite)) if finite else math.nan

    def means(triples: list[tuple[float, float, float]]) -> tuple[float, float, float]:
        return (mean([x[0] for x in triples]), mean([x[1] for x in triples]), mean([x[2] for x in triples]))

    headline = [t for v, t in per_variant.items() if in_aggregate(v)]
    return RankingStability(len(names), *means(headline), {a: means(p) for a, p in per_axis.items()})


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
