"""MMRV and Pearson r as SimplerEnv defines them (simpler_env/utils/metrics.py), computed
where SimplerEnv computes them (tools/calc_metrics_evaluation_videos.py): once per task,
on the success aggregated over the task's own set of settings, the base scene included.

The references below are written here from SimplerEnv's text, loop by loop, not imported:
the canonical scene plays SimplerEnv's real-world side (`perf_real`, whose gaps MMRV
weighs) and the aggregate its simulation side (`perf_sim`). Ties are where a careless
version differs (state policies score alike under every visual axis), so the cases are
tie-heavy on purpose, with constant, short, empty and NaN vectors beside them."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pandas as pd
import pytest

from adapters.simpler_variants import HARNESS_AXES, SIMPLERENV_AXES, simplerenv_set
from results.variant_table import CANONICAL, mmrv, pearson_r, ranking_stability, variant_stats


def reference_mmrv(sim: list[float], real: list[float]) -> float:
    """SimplerEnv's mean_maximum_rank_violation: for each policy i, a running Python `max`
    of |real_i - real_j| over the j where (sim_i > sim_j) != (real_i > real_j), starting
    at 0.0; numpy's mean of those (NaN, with a warning, for no policies)."""
    sim_a, real_a = np.array(sim, float), np.array(real, float)
    worst = []
    for i in range(len(sim_a)):
        violation = 0.0
        for j in range(len(sim_a)):
            if (sim_a[i] > sim_a[j]) != (real_a[i] > real_a[j]):
                violation = max(violation, np.abs(real_a[i] - real_a[j]))
        worst.append(violation)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return float(np.mean(worst))


def reference_pearson(sim: list[float], real: list[float]) -> float:
    """SimplerEnv's pearson_correlation: centre both; 1 if the centred vectors are equal
    element for element (np.all, so also for none), else
    sum(x y) / (sqrt(sum x^2 * sum y^2) + 1e-8)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        x = np.array(sim, float) - np.mean(np.array(sim, float))
        y = np.array(real, float) - np.mean(np.array(real, float))
    if np.all(x == y):
        return 1.0
    return float(np.sum(x * y) / (np.sqrt(np.sum(x**2) * np.sum(y**2)) + 1e-8))


def same(a: float, b: float, tol: float = 1e-12) -> bool:
    return (math.isnan(a) and math.isnan(b)) or abs(a - b) <= tol


def both(canonical: list[float], aggregate: list[float]) -> tuple[float, float]:
    return mmrv(np.array(canonical), np.array(aggregate)), pearson_r(np.array(canonical), np.array(aggregate))


def test_the_worked_examples():
    # canonical [0.1, 0.2, 0.9] against an aggregate tying them all: policy 1 loses the 0.1 gap
    # to policy 0, policy 2 the 0.8 gap to policy 0; a `<` test would give 0.5
    assert mmrv(np.array([0.1, 0.2, 0.9]), np.array([0.3, 0.3, 0.3])) == pytest.approx(0.3)
    assert pearson_r(np.array([0.1, 0.2, 0.9]), np.array([0.3, 0.3, 0.3])) == 0.0  # constant vs varying
    canonical = [15 / 24, 16 / 24, 16 / 24, 16 / 24, 9 / 24]
    aggregate = [16 / 24, 16 / 24, 16 / 24, 15 / 24, 9 / 24]
    assert mmrv(np.array(canonical), np.array(aggregate)) == pytest.approx(
        reference_mmrv(aggregate, canonical)
    )
    assert mmrv(np.array(canonical), np.array(aggregate)) == pytest.approx(1 / 30, abs=1e-4)


@pytest.mark.parametrize(
    "canonical, aggregate",
    [
        ([0.5, 0.5, 0.5], [0.5, 0.5, 0.5]),  # all equal
        ([0.2, 0.2, 0.2, 0.2], [0.0, 0.0, 0.0, 0.0]),  # both constant, different levels
        ([0.2, 0.4, 0.6], [0.3, 0.3, 0.3]),  # aggregate constant
        ([0.3, 0.3, 0.3], [0.2, 0.4, 0.6]),  # canonical constant
        ([0.1, 0.2, 0.3], [0.2, 0.3, 0.4]),  # shifted: equal once centred
        ([0.5, 0.5, 0.9, 0.1], [0.5, 0.6, 0.9, 0.1]),  # a tie broken
        ([0.5, 0.6, 0.9, 0.1], [0.5, 0.5, 0.9, 0.1]),  # a tie made
        ([1.0, 0.0], [0.0, 1.0]),  # reversed
        ([0.25, 0.25, 0.75, 0.75], [0.75, 0.75, 0.25, 0.25]),
        ([0.7], [0.2]),  # one policy: MMRV 0, r 1
        ([], []),  # none: MMRV NaN, r 1
        ([0.5, math.nan, 0.2], [0.4, 0.6, 0.1]),  # NaN in the reference: its gaps never count
        ([math.nan, 0.9, 0.1, 0.4], [0.3, 0.1, 0.9, 0.4]),
        ([math.nan, math.nan], [0.3, 0.1]),
        ([0.5, 0.6, 0.2], [0.4, math.nan, 0.1]),  # NaN on the aggregate side: compares as a tie
    ],
)
def test_edge_cases_equal_simplerenvs_definitions(canonical, aggregate):
    got_mmrv, got_pearson = both(canonical, aggregate)
    assert same(got_mmrv, reference_mmrv(aggregate, canonical))
    assert same(got_pearson, reference_pearson(aggregate, canonical))


def test_short_empty_and_nan_conventions_spelled_out():
    assert both([0.7], [0.2]) == (0.0, 1.0)
    got_mmrv, got_pearson = both([], [])
    assert math.isnan(got_mmrv) and got_pearson == 1.0
    # a NaN reference rate: no gap to it counts (upstream's max(0.0, nan) keeps 0.0), the
    # mean still counts its policy; Pearson r is NaN
    assert mmrv(np.array([0.5, math.nan, 0.2]), np.array([0.1, 0.6, 0.4])) == pytest.approx(
        (0.3 + 0 + 0.3) / 3
    )
    assert math.isnan(pearson_r(np.array([0.5, math.nan, 0.2]), np.array([0.1, 0.6, 0.4])))
    assert both([0.2, 0.2], [0.9, 0.9]) == (0.0, 1.0)  # constant against constant: 1, not NaN
    assert pearson_r(np.array([0.1, 0.2, 0.3]), np.array([0.2, 0.3, 0.4])) == pytest.approx(
        1 - 5e-7, abs=1e-9
    )


def test_random_cases_with_ties_and_nans_equal_simplerenvs_definitions():
    """2,000 cases of 0-6 policies with success rates in 24ths (so ties are common), one
    in ten with a NaN on either side."""
    rng = np.random.default_rng(46)
    for _ in range(2000):
        n = int(rng.integers(0, 7))
        canonical = rng.integers(0, 25, n) / 24
        aggregate = rng.integers(0, 25, n) / 24
        if n and rng.random() < 0.1:
            (canonical if rng.random() < 0.5 else aggregate)[rng.integers(0, n)] = math.nan
        got_mmrv, got_pearson = both(canonical.tolist(), aggregate.tolist())
        assert same(got_mmrv, reference_mmrv(aggregate.tolist(), canonical.tolist()))
        assert same(got_pearson, reference_pearson(aggregate.tolist(), canonical.tolist()), 1e-9)


# --- where the metrics are computed: per task, on the aggregate ----------------------------


def _rows(rates: dict[str, dict[str, list[float]]], layouts: int = 4) -> dict[str, pd.DataFrame]:
    """policy -> task -> per-setting success (a list aligned with the task's set) as rows."""
    out = {}
    for policy, per_task in rates.items():
        rows = []
        for task, values in per_task.items():
            settings = [v.label for v in simplerenv_set(task)]
            for setting, rate in zip(settings, values, strict=True):
                rows += [
                    {"task": task, "variant": setting, "seed": j, "success": j < round(rate * layouts)}
                    for j in range(layouts)
                ]
        out[policy] = pd.DataFrame(rows)
    return out


def simplerenv_pipeline(per_setting: dict[str, dict[str, list[float]]], task: str) -> tuple[float, float]:
    """SimplerEnv's calc_*_stats, from its text: each policy's flat mean over the task's
    settings (base first), then the metrics once against the reference (here canonical)."""
    policies = list(per_setting)
    sim = [float(np.mean(per_setting[p][task])) for p in policies]
    real = [per_setting[p][task][0] for p in policies]
    return reference_mmrv(sim, real), reference_pearson(sim, real)


def test_two_opposite_variants_average_out_on_the_aggregate_but_not_per_variant():
    """Canonical [0.5, 0.6, 0.7]; one background reverses them ([0.7, 0.6, 0.5]), the other
    spreads them ([0.3, 0.6, 0.9]): the aggregate keeps the canonical order (SimplerEnv:
    MMRV 0, r 1), where a mean of per-variant metrics reports a violation and r 0."""
    base = [0.5, 0.6, 0.7]
    rev, spread = [0.7, 0.6, 0.5], [0.3, 0.6, 0.9]
    rates = {}
    for i, name in enumerate("abc"):
        # push_cube's set: canonical, background dark, sand, ...; the rest as canonical
        rest = [base[i]] * (len(simplerenv_set("push_cube")) - 3)
        rates[name] = {"push_cube": [base[i], rev[i], spread[i], *rest]}
    stats = {p: variant_stats(r) for p, r in _rows(rates, layouts=10).items()}
    r = ranking_stability(stats)
    assert r.per_task["push_cube"][:2] == (0.0, pytest.approx(1.0, abs=1e-6))
    assert (r.mmrv, r.pearson) == pytest.approx(simplerenv_pipeline(rates, "push_cube"))
    # the per-variant diagnostic, 0.083 and 0.0: reversed (0.2 + 0.1 + 0.2) / 3
    # and r -1, spread 0 and r 1, averaged over the two backgrounds
    assert r.per_axis["background"][:2] == (pytest.approx(0.5 / 3 / 2), pytest.approx(0.0, abs=1e-6))


def test_random_runs_equal_simplerenvs_pipeline_per_task():
    rng = np.random.default_rng(7)
    tasks = ("pick_cube", "push_cube")
    for _ in range(10):
        n = int(rng.integers(2, 6))
        rates = {
            f"p{k}": {t: (rng.integers(0, 5, len(simplerenv_set(t))) / 4).tolist() for t in tasks}
            for k in range(n)
        }
        r = ranking_stability({p: variant_stats(rows) for p, rows in _rows(rates).items()})
        for task in tasks:
            want_mmrv, want_r = simplerenv_pipeline(rates, task)
            assert same(r.per_task[task][0], want_mmrv) and same(r.per_task[task][1], want_r, 1e-9)
        # over tasks: the metric on the task means, as SimplerEnv's "avg" over orientations
        sim = [np.mean([np.mean(rates[p][t]) for t in tasks]) for p in rates]
        real = [np.mean([rates[p][t][0] for t in tasks]) for p in rates]
        assert same(r.mmrv, reference_mmrv(sim, real)) and same(r.pearson, reference_pearson(sim, real), 1e-9)


# --- which settings the aggregate counts -----------------------------------------------------


def test_each_task_follows_one_simplerenv_set_of_its_size():
    """coke can 9 settings (2 distractor settings), move near 8 (1): 2 backgrounds, 2
    lightings, 2 tables, the canonical scene."""
    assert len(simplerenv_set("pick_cube")) == 9
    for task in ("push_cube", "pull_cube", "stack_cube", "place_sphere"):
        labels = [v.label for v in simplerenv_set(task)]
        assert len(labels) == 8 and sum(x.startswith("distractors=") for x in labels) == 1
    labels = [v.label for v in simplerenv_set("pick_cube")]
    for axis, count in (("background", 2), ("lighting", 2), ("table", 2), ("distractors", 2)):
        assert sum(x.startswith(axis + "=") for x in labels) == count
    assert "lighting=warm" not in labels and "table=green" not in labels


def test_the_default_aggregate_is_each_tasks_set_then_the_mean_over_tasks():
    pick = {v.label: 1.0 for v in simplerenv_set("pick_cube")} | {"lighting=dim": 0.0}
    push = {v.label: 0.5 for v in simplerenv_set("push_cube")}
    extra = {"lighting=warm": 0.0, "table=green": 0.0, "camera=left": 0.0}
    rows = pd.DataFrame(
        [
            {"task": task, "variant": v, "seed": j, "success": j < rate * 4}
            for task, rates in (
                ("pick_cube", pick | extra),
                ("push_cube", push | extra | {"distractors=three": 0}),
            )
            for v, rate in rates.items()
            for j in range(4)
        ]
    )
    stats = variant_stats(rows)
    assert stats.task_aggregate("pick_cube") == pytest.approx(8 / 9)
    assert stats.task_aggregate("push_cube") == pytest.approx(0.5)  # distractors=three is not in its set
    assert stats.aggregated == pytest.approx((8 / 9 + 0.5) / 2)
    # extended: every level of SimplerEnv's axes that ran, camera left out
    assert stats.task_extended("pick_cube") == pytest.approx(8 / 11)
    assert stats.task_extended("push_cube") == pytest.approx(4 / 11)
    assert stats.extended == pytest.approx((8 / 11 + 4 / 11) / 2)
    low, high = stats.aggregated_interval
    assert low <= stats.aggregated <= high
    # a run without the whole set has no SimplerEnv aggregate, only the extended one
    partial = variant_stats(rows[rows["variant"].isin([CANONICAL, "lighting=dim", "camera=left"])])
    assert math.isnan(partial.aggregated) and partial.aggregated_text() == "-"
    assert partial.extended == pytest.approx(((1 + 0) / 2 + 0.5) / 2)
    only_ours = variant_stats(rows[rows["variant"].isin([CANONICAL, "camera=left"])])
    assert math.isnan(only_ours.extended)  # the canonical scene alone is no aggregate


def test_every_variant_axis_is_either_simplerenvs_or_the_harnesss_own():
    """A new axis in the variants file must be classified: in the aggregate or apart."""
    from adapters import simpler_variants as sv

    axes = sv.axes()
    assert set(axes) == set(SIMPLERENV_AXES) | set(HARNESS_AXES)
    assert {a for a in axes if axes[a].kind == "physical"} <= set(HARNESS_AXES)
