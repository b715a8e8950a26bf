"""SimplerEnv-like variant runs in SimplerEnv's terms: success in the canonical scene,
variant-aggregated success per task and over tasks, the drop per axis, and whether the
aggregate ranks policies as the canonical scene does (MMRV, Pearson r, Kendall tau).

The canonical scene is ManiSkill3's own default scene. It is not SimplerEnv's "visual
matching" (real images overlaid on the simulator, robot colourings averaged), which needs
real-world footage this harness does not have; it only plays that role as the reference.

Aggregated success is SimplerEnv's variant aggregation (tools/calc_metrics_evaluation_
videos.py), computed where SimplerEnv computes it: per task, the flat mean over that
task's own set of settings, the canonical (base) scene included (the SimplerEnv task each
ManiSkill3 task follows, and its set: adapters/simpler_data/simplerenv_sets.toml; 9
settings for a pick-coke-can analogue, 8 for move near), then the mean over tasks. A task
that did not run every setting of its set has no aggregate ("-"): SimplerEnv's number is
over its set, not over whatever ran. The extended aggregate is the same per-task mean
over the canonical scene and every setting of SimplerEnv's four axes that ran
(backgrounds, lighting, distractors, table textures), the levels outside the set
included. Camera poses and the physical axes (friction, mass) are the harness's own
robustness axes: SimplerEnv leaves camera out of its aggregate and has no physical
variants, so they are reported per axis only, never averaged in. The interval is a
percentile bootstrap over layouts (a task's seed), stratified by task: every setting
replays the same layouts, so outcomes under different settings of one layout are not
independent, and resampling layouts, not episodes, keeps that. The seed is fixed, so the
same rows always print the same interval.

Ranking stability is SimplerEnv's: per task, the policies' aggregated success (S, in the
role of SimplerEnv's simulated success) against their canonical success (R, the
reference, in the role of real-world success), with SimplerEnv's own functions
(simpler_env/utils/metrics.py), and once over tasks on the task means (as SimplerEnv
combines a task's coke-can orientations or its open and close drawers):

    MMRV = 1/N sum_i max_j |R_i - R_j| * 1[(S_i > S_j) != (R_i > R_j)]

the largest reference gap the aggregate inverts, averaged over policies (0 = same order;
in success units). Strict `>` on both sides: a pair tied under one and ordered under the
other counts as a violation. Pearson's r is computed on the centred vectors: 1 when they
are equal after centring (two constant vectors, one policy, none), else
sum(r s) / (sqrt(sum r^2 sum s^2) + 1e-8), so a constant vector against a varying one
gives 0. Kendall's tau-b is given beside them (1 = same order). The same metrics per
variant against the canonical scene, averaged over an axis's levels, are a diagnostic
of where an order changes, not SimplerEnv's figures.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import pandas as pd

from adapters.simpler_variants import SIMPLERENV_AXES, VariantError, simplerenv_set
from results.render import Cell, finite_or_none
from results.summary import Success

CANONICAL = "canonical"
BOOTSTRAP_RESAMPLES = 10_000
BOOTSTRAP_SEED = 0


def axis_of(variant: str) -> str:
    return variant.split("=", 1)[0]


def in_extended(variant: str) -> bool:
    """Whether a setting counts in the extended aggregate (the canonical scene does)."""
    return variant == CANONICAL or axis_of(variant) in SIMPLERENV_AXES


def simplerenv_settings(task: str) -> tuple[str, ...] | None:
    """The `variant` labels of a task's SimplerEnv set, the canonical first; None for a
    task that follows no SimplerEnv task."""
    try:
        return tuple(v.label for v in simplerenv_set(task))
    except VariantError:
        return None


def is_variant_run(episodes: pd.DataFrame) -> bool:
    """Rows that ran under more than the canonical scene."""
    if "variant" not in episodes:
        return False
    seen = set(episodes["variant"].dropna())
    return bool(seen - {CANONICAL})


def _mean_or_nan(values: list[float]) -> float:
    return float(np.mean(values)) if values and not any(math.isnan(v) for v in values) else math.nan


@dataclass(frozen=True)
class VariantStats:
    canonical: Success  # the canonical scene's episodes, every task
    per_variant: dict[str, float]  # variant label -> success rate over every task (canonical included)
    per_task: dict[str, dict[str, float]]  # task -> variant label -> success rate
    aggregated: float  # SimplerEnv's: each task's set, then the mean over tasks
    aggregated_interval: tuple[float, float]
    extended: float  # the canonical scene and every level of SimplerEnv's axes that ran, likewise
    extended_interval: tuple[float, float]

    def task_aggregate(self, task: str) -> float:
        """SimplerEnv's aggregate of one task: the mean over its set; NaN unless all of it ran."""
        return _set_mean(task, self.per_task[task])

    def task_extended(self, task: str) -> float:
        return _extended_mean(self.per_task[task])

    def task_canonical(self, task: str) -> float:
        return self.per_task[task].get(CANONICAL, math.nan)

    def per_axis(self) -> dict[str, float]:
        """Mean success over each axis's levels, in the order the variants came."""
        axes: dict[str, list[float]] = {}
        for label, rate in self.per_variant.items():
            if label != CANONICAL:
                axes.setdefault(axis_of(label), []).append(rate)
        return {axis: float(np.mean(rates)) for axis, rates in axes.items()}

    def aggregated_text(self) -> str:
        return _interval_text(self.aggregated, self.aggregated_interval)

    def extended_text(self) -> str:
        return _interval_text(self.extended, self.extended_interval)

    def axis_text(self, axis: str) -> str:
        rate = self.per_axis().get(axis)
        if rate is None:
            return "-"
        return f"{100 * rate:.1f}% ({100 * (rate - self.canonical.rate):+.1f})"


def _interval_text(value: float, interval: tuple[float, float]) -> str:
    if math.isnan(value):
        return "-"
    low, high = interval
    return f"{100 * value:.1f}% [{100 * low:.0f}, {100 * high:.0f}]"


def _set_mean(task: str, rates: Mapping[str, float]) -> float:
    settings = simplerenv_settings(task)
    if settings is None or not all(s in rates for s in settings):
        return math.nan
    return float(np.mean([rates[s] for s in settings]))


def _extended_mean(rates: Mapping[str, float]) -> float:
    counted = [v for v in rates if in_extended(v)]
    if not any(v != CANONICAL for v in counted):
        return math.nan  # the canonical scene alone is no aggregate
    return float(np.mean([rates[v] for v in counted]))


def _bootstrap(rows: pd.DataFrame, settings_of: Mapping[str, list[str]]) -> tuple[float, float]:
    """Percentile 95% interval of the mean over tasks of each task's flat mean over its
    settings, resampling each task's layouts (seeds) with replacement."""
    rng = np.random.default_rng(BOOTSTRAP_SEED)
    per_task = []
    for task, settings in settings_of.items():
        mine = rows[(rows["task"] == task) & rows["variant"].isin(settings)]
        table = mine.pivot_table(index="variant", columns="seed", values="ok", aggfunc="mean")
        matrix = table.to_numpy(dtype=float)  # settings x layouts; NaN where a setting skipped one
        picks = rng.integers(0, matrix.shape[1], size=(BOOTSTRAP_RESAMPLES, matrix.shape[1]))
        with np.errstate(invalid="ignore"):
            per_task.append(np.nanmean(np.nanmean(matrix[:, picks], axis=2), axis=0))
    low, high = np.nanpercentile(np.mean(per_task, axis=0), [2.5, 97.5])
    return float(low), float(high)


def variant_stats(rows: pd.DataFrame) -> VariantStats:
    """One policy configuration's rows (any tasks): success per variant and per task, and
    SimplerEnv's aggregate and the extended one, each with a bootstrap over layouts."""
    rows = rows[rows["variant"].notna()].assign(ok=lambda r: r["success"].astype(float))
    per_variant = {str(v): float(g.mean()) for v, g in rows["ok"].groupby(rows["variant"], sort=False)}
    per_task: dict[str, dict[str, float]] = {}
    for (task, variant), group in rows.groupby(["task", "variant"], sort=False):
        per_task.setdefault(str(task), {})[str(variant)] = float(group["ok"].mean())
    aggregated = _mean_or_nan([_set_mean(t, rates) for t, rates in per_task.items()])
    extended = _mean_or_nan([_extended_mean(rates) for rates in per_task.values()])
    nan = (math.nan, math.nan)
    set_interval = nan
    if not math.isnan(aggregated):
        set_interval = _bootstrap(rows, {t: list(simplerenv_settings(t) or ()) for t in per_task})
    extended_interval = nan
    if not math.isnan(extended):
        extended_interval = _bootstrap(
            rows, {t: [v for v in r if in_extended(v)] for t, r in per_task.items()}
        )
    canonical = rows[rows["variant"] == CANONICAL]
    return VariantStats(
        Success(int(canonical["success"].sum()), len(canonical)),
        per_variant,
        per_task,
        aggregated,
        set_interval,
        extended,
        extended_interval,
    )


# --- SimplerEnv's metrics ----------------------------------------------------------------


def mmrv(reference: np.ndarray, other: np.ndarray) -> float:
    """SimplerEnv's mean maximum rank violation of `other` (its simulated side) against
    `reference` (its real side, whose gaps are weighed), with its conventions: one policy
    gives 0, none NaN; a gap involving a NaN reference never counts (upstream's running
    `max` keeps the larger of a number and NaN only when the number comes second)."""
    r, s = np.asarray(reference, float), np.asarray(other, float)
    if r.shape != s.shape:
        raise ValueError(f"mmrv: {len(r)} reference rates against {len(s)} others")
    if len(r) == 0:
        return math.nan
    violated = (s[:, None] > s[None, :]) != (r[:, None] > r[None, :])
    gaps = np.abs(r[:, None] - r[None, :])
    counted = np.where(violated & ~np.isnan(gaps), gaps, 0.0)
    return float(np.mean(np.max(counted, axis=1)))


def pearson_r(reference: np.ndarray, other: np.ndarray) -> float:
    """Pearson's r with SimplerEnv's conventions, so that tied policies (state policies
    score alike under every visual axis) print what SimplerEnv would: 1 when the centred
    vectors are equal (two constant ones, one policy, none), 0 for a constant against a
    varying one, NaN where either holds a NaN."""
    r, s = np.asarray(reference, float), np.asarray(other, float)
    if r.shape != s.shape:
        raise ValueError(f"pearson_r: {len(r)} reference rates against {len(s)} others")
    if len(r) == 0:
        return 1.0  # upstream: every one of no centred values is equal
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


Triple = tuple[float, float, float]  # MMRV, Pearson r, Kendall tau


def _metrics(reference: np.ndarray, other: np.ndarray) -> Triple:
    if np.isnan(other).all():  # no aggregate to compare (the set did not run)
        return (math.nan, math.nan, math.nan)
    return (mmrv(reference, other), pearson_r(reference, other), kendall_tau(reference, other))


@dataclass(frozen=True)
class RankingStability:
    """SimplerEnv's metrics on the aggregated success per task and over tasks; the extended
    aggregate's beside them; per-variant figures per axis as a diagnostic."""

    policies: int
    mmrv: float  # over tasks, on the task means of SimplerEnv's aggregate and of canonical success
    pearson: float  # likewise
    kendall_tau: float  # likewise, where it is defined
    per_task: dict[str, Triple]  # task -> (MMRV, Pearson r, tau) of SimplerEnv's aggregate
    extended: Triple  # over tasks, on the extended aggregate
    per_axis: dict[str, Triple]  # diagnostic: each variant against canonical, mean over the axis's levels

    def text(self) -> str:
        if self.policies < 2:
            return "ranking stability: n/a (one policy configuration; it needs two or more)"

        def triple(t: Triple) -> str:
            return f"{_num(t[0], 3)} / {_num(t[1])} / {_num(t[2])}"

        def axes(names: list[str]) -> str:
            return "; ".join(f"{a} {triple(t)}" for a, t in self.per_axis.items() if a in names)

        headline = (self.mmrv, self.pearson, self.kendall_tau)
        text = (
            f"ranking stability of the variant aggregate vs the canonical scene over {self.policies} "
            f"policy configurations, SimplerEnv's metrics per task on each task's set: MMRV "
            f"{_num(self.mmrv, 3)} (0 = same order), Pearson r {_num(self.pearson)}, Kendall tau "
            f"{_num(self.kendall_tau)} (1 = same order) over tasks"
        )
        if len(self.per_task) > 1 or math.isnan(headline[0]):
            text += "; per task MMRV / Pearson r / tau: " + "; ".join(
                f"{task} {triple(t)}" for task, t in self.per_task.items()
            )
        if self.extended != headline:
            text += f"; extended aggregate {triple(self.extended)}"
        ours = [a for a in self.per_axis if a not in SIMPLERENV_AXES]
        text += (
            "; diagnostic, each variant against the canonical scene, mean per axis: "
            f"{axes(list(SIMPLERENV_AXES)) or 'none run'}"
        )
        if ours:
            text += f"; the harness's own axes, not in SimplerEnv's aggregate: {axes(ours)}"
        return text


def _num(value: float, decimals: int = 2) -> str:
    return "-" if math.isnan(value) else f"{value:.{decimals}f}"


def _axis_means(triples: list[Triple]) -> Triple:
    def mean(values: list[float]) -> float:
        finite = [x for x in values if not math.isnan(x)]
        return float(np.mean(finite)) if finite else math.nan

    return (mean([x[0] for x in triples]), mean([x[1] for x in triples]), mean([x[2] for x in triples]))


def ranking_stability(stats: Mapping[str, VariantStats]) -> RankingStability:
    """From each policy configuration's VariantStats (keyed by configuration), over the
    tasks every configuration ran."""
    names = list(stats)
    every = [set(s.per_task) for s in stats.values()]
    tasks = [t for t in (next(iter(stats.values())).per_task if stats else ()) if all(t in e for e in every)]

    def vector(value) -> np.ndarray:
        return np.array([[value(stats[n], t) for t in tasks] for n in names], dtype=float).reshape(
            len(names), -1
        )

    canonical = vector(VariantStats.task_canonical)
    aggregate = vector(VariantStats.task_aggregate)
    extended = vector(VariantStats.task_extended)
    per_task = {t: _metrics(canonical[:, k], aggregate[:, k]) for k, t in enumerate(tasks)}
    with np.errstate(invalid="ignore"):
        over_tasks = _metrics(canonical.mean(axis=1), aggregate.mean(axis=1))
        over_tasks_extended = _metrics(canonical.mean(axis=1), extended.mean(axis=1))
    variants = [v for v in next(iter(stats.values())).per_variant if v != CANONICAL] if stats else []
    variants = [v for v in variants if all(v in s.per_variant for s in stats.values())]
    reference = np.array([stats[n].canonical.rate for n in names])
    per_axis: dict[str, list[Triple]] = {}
    for v in variants:
        other = np.array([stats[n].per_variant[v] for n in names])
        per_axis.setdefault(axis_of(v), []).append(_metrics(reference, other))
    return RankingStability(
        len(names),
        *over_tasks,
        per_task,
        over_tasks_extended,
        {a: _axis_means(t) for a, t in per_axis.items()},
    )


# --- cells for leaderboards (results/leaderboard.py) -------------------------------------


def variant_cells(stats: VariantStats | None, axes: tuple[str, ...]) -> list[Cell]:
    if stats is None:
        return [Cell("-", None)] * (3 + len(axes))
    per_axis = stats.per_axis()
    return [
        Cell(stats.canonical.text(), finite_or_none(stats.canonical.rate)),
        Cell(stats.aggregated_text(), finite_or_none(stats.aggregated)),
        Cell(stats.extended_text(), finite_or_none(stats.extended)),
        *(Cell(stats.axis_text(a), finite_or_none(per_axis.get(a, math.nan))) for a in axes),
    ]


def variant_columns(stats: VariantStats) -> dict[str, float]:
    low, high = stats.canonical.interval
    agg_low, agg_high = stats.aggregated_interval
    ext_low, ext_high = stats.extended_interval
    out = {
        "canonical_success": stats.canonical.rate,
        "canonical_low": low,
        "canonical_high": high,
        "aggregated_success": stats.aggregated,
        "aggregated_low": agg_low,
        "aggregated_high": agg_high,
        "extended_aggregated_success": stats.extended,
        "extended_aggregated_low": ext_low,
        "extended_aggregated_high": ext_high,
    }
    out |= {f"aggregated_success[{t}]": stats.task_aggregate(t) for t in stats.per_task}
    out |= {f"success[{a}]": rate for a, rate in stats.per_axis().items()}
    return out | {f"success[{v}]": rate for v, rate in stats.per_variant.items()}
