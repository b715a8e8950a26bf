"""MMRV and Pearson r as SimplerEnv defines them (simpler_env/utils/metrics.py), and
SimplerEnv's variant aggregation set.

The references below are written here from SimplerEnv's definitions, loop by loop, not
imported: the canonical scene plays SimplerEnv's real-world side (`perf_real`, whose gaps
MMRV weighs) and a variant its simulation side (`perf_sim`). Ties are where a careless
version differs (state policies score alike under every visual axis), so the cases are
tie-heavy on purpose."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from results.variant_table import (
    CANONICAL,
    HARNESS_AXES,
    SIMPLERENV_AXES,
    mmrv,
    pearson_r,
    ranking_stability,
    variant_stats,
)


def reference_mmrv(sim: list[float], real: list[float]) -> float:
    """SimplerEnv's mean_maximum_rank_violation: for each policy i, the largest
    |real_i - real_j| over the j where (sim_i > sim_j) != (real_i > real_j); the mean."""
    worst = []
    for i in range(len(sim)):
        violation = 0.0
        for j in range(len(sim)):
            if (sim[i] > sim[j]) != (real[i] > real[j]):
                violation = max(violation, abs(real[i] - real[j]))
        worst.append(violation)
    return sum(worst) / len(worst)


def reference_pearson(sim: list[float], real: list[float]) -> float:
    """SimplerEnv's pearson_correlation: centre both; 1 if the centred vectors are equal
    element for element, else sum(x y) / (sqrt(sum x^2 * sum y^2) + 1e-8)."""
    x = np.array(sim, float) - np.mean(sim)
    y = np.array(real, float) - np.mean(real)
    if all(a == b for a, b in zip(x, y, strict=True)):
        return 1.0
    return float(sum(a * b for a, b in zip(x, y, strict=True)) / (math.sqrt(sum(x * x) * sum(y * y)) + 1e-8))


def both(canonical: list[float], variant: list[float]) -> tuple[float, float]:
    return mmrv(np.array(canonical), np.array(variant)), pearson_r(np.array(canonical), np.array(variant))


def test_the_worked_examples():
    # canonical [0.1, 0.2, 0.9] against a variant tying them all: policy 1 loses the 0.1 gap
    # to policy 0, policy 2 the 0.8 gap to policy 0; a `<` test would give 0.5
    assert mmrv(np.array([0.1, 0.2, 0.9]), np.array([0.3, 0.3, 0.3])) == pytest.approx(0.3)
    assert pearson_r(np.array([0.1, 0.2, 0.9]), np.array([0.3, 0.3, 0.3])) == 0.0  # constant vs varying
    # the five state decoders of docs/simpler.md, canonical 15, 16, 16, 16, 9 of 24; a variant
    # where the three tied at the top split 16, 16, 15 and the teacher reaches 16
    canonical = [15 / 24, 16 / 24, 16 / 24, 16 / 24, 9 / 24]
    variant = [16 / 24, 16 / 24, 16 / 24, 15 / 24, 9 / 24]
    assert mmrv(np.array(canonical), np.array(variant)) == pytest.approx(reference_mmrv(variant, canonical))
    assert mmrv(np.array(canonical), np.array(variant)) == pytest.approx(1 / 30, abs=1e-4)  # 0.0333


@pytest.mark.parametrize(
    "canonical, variant",
    [
        ([0.5, 0.5, 0.5], [0.5, 0.5, 0.5]),  # all equal
        ([0.2, 0.2, 0.2, 0.2], [0.0, 0.0, 0.0, 0.0]),  # both constant, different levels
        ([0.2, 0.4, 0.6], [0.3, 0.3, 0.3]),  # variant constant
        ([0.3, 0.3, 0.3], [0.2, 0.4, 0.6]),  # canonical constant
        ([0.1, 0.2, 0.3], [0.2, 0.3, 0.4]),  # shifted: equal once centred
        ([0.5, 0.5, 0.9, 0.1], [0.5, 0.6, 0.9, 0.1]),  # a tie broken
        ([0.5, 0.6, 0.9, 0.1], [0.5, 0.5, 0.9, 0.1]),  # a tie made
        ([1.0, 0.0], [0.0, 1.0]),  # reversed
        ([0.25, 0.25, 0.75, 0.75], [0.75, 0.75, 0.25, 0.25]),
    ],
)
def test_tie_heavy_cases_equal_simplerenvs_definitions(canonical, variant):
    got_mmrv, got_pearson = both(canonical, variant)
    assert got_mmrv == pytest.approx(reference_mmrv(variant, canonical), abs=1e-12)
    assert got_pearson == pytest.approx(reference_pearson(variant, canonical), abs=1e-12)


def test_identical_and_constant_vectors_follow_simplerenvs_conventions():
    assert both([0.5, 0.5, 0.5], [0.5, 0.5, 0.5]) == (0.0, 1.0)
    assert both([0.2, 0.2], [0.9, 0.9]) == (0.0, 1.0)  # constant against constant: 1, not NaN
    assert both([0.2, 0.8], [0.4, 0.4])[1] == 0.0  # constant against varying: 0, not NaN
    assert both([0.25, 0.5, 0.75], [0.5, 0.75, 1.0]) == (0.0, 1.0)  # equal once centred (exactly)
    # equal once centred only up to rounding: SimplerEnv's formula, 1e-8 in the denominator
    assert pearson_r(np.array([0.1, 0.2, 0.3]), np.array([0.2, 0.3, 0.4])) == pytest.approx(
        1 - 5e-7, abs=1e-9
    )


def test_random_24_episode_cases_equal_simplerenvs_definitions():
    """2,000 cases of 2-6 policies with success rates in 24ths (24 episodes each, so ties
    are common); a `<`-based MMRV differs on many of these."""
    rng = np.random.default_rng(46)
    differ_from_less_than = 0
    for _ in range(2000):
        n = int(rng.integers(2, 7))
        canonical = (rng.integers(0, 25, n) / 24).tolist()
        variant = (rng.integers(0, 25, n) / 24).tolist()
        got_mmrv, got_pearson = both(canonical, variant)
        assert got_mmrv == pytest.approx(reference_mmrv(variant, canonical), abs=1e-12)
        assert got_pearson == pytest.approx(reference_pearson(variant, canonical), abs=1e-9)
        r, s = np.array(canonical), np.array(variant)
        less = (r[:, None] < r[None, :]) != (s[:, None] < s[None, :])
        old = float(np.mean(np.max(np.abs(r[:, None] - r[None, :]) * less, axis=1)))
        differ_from_less_than += not math.isclose(old, got_mmrv)
    assert differ_from_less_than > 100  # the cases do exercise ties


def test_the_default_aggregate_is_simplerenvs_set():
    """SimplerEnv averages the base scene, backgrounds, lighting, distractors and table
    textures; camera is left out and it has no physical variants."""
    assert set(SIMPLERENV_AXES) == {"background", "lighting", "distractors", "table"}
    assert set(HARNESS_AXES) == {"camera", "friction", "mass"}
    settings = {
        CANONICAL: 1.0,
        "lighting=dim": 0.5,
        "table=white": 0.25,
        "distractors=one": 1.0,
        "camera=left": 0.0,
        "friction=low": 0.0,
        "mass=heavy": 0.0,
    }
    rows = pd.DataFrame(
        [
            {"variant": v, "task": "push_cube", "seed": j, "success": j < rate * 4}
            for v, rate in settings.items()
            for j in range(4)
        ]
    )
    stats = variant_stats(rows)
    assert stats.aggregated == pytest.approx((1.0 + 0.5 + 0.25 + 1.0) / 4)
    assert set(stats.per_axis()) == {"lighting", "table", "distractors", "camera", "friction", "mass"}
    only_ours = variant_stats(rows[rows["variant"].isin([CANONICAL, "camera=left", "mass=heavy"])])
    assert math.isnan(only_ours.aggregated)  # the canonical scene alone is no aggregate


def test_the_headline_ranking_numbers_leave_the_harness_axes_out():
    def rows(rates: dict[str, float]) -> pd.DataFrame:
        return pd.DataFrame(
            [
                {"variant": v, "task": "push_cube", "seed": j, "success": j < rate * 4}
                for v, rate in rates.items()
                for j in range(4)
            ]
        )

    a = variant_stats(rows({CANONICAL: 1.0, "lighting=dim": 1.0, "camera=left": 0.0}))
    b = variant_stats(rows({CANONICAL: 0.5, "lighting=dim": 0.5, "camera=left": 1.0}))
    r = ranking_stability({"a": a, "b": b})
    assert (r.mmrv, r.pearson, r.kendall_tau) == (0.0, 1.0, 1.0)  # lighting keeps the order
    assert r.per_axis["camera"] == (0.5, pytest.approx(-1.0), -1.0)  # camera reverses it
    assert "not in SimplerEnv's aggregate: camera 0.500" in r.text()


def test_every_variant_axis_is_either_simplerenvs_or_the_harnesss_own():
    """A new axis in the variants file must be classified: in the aggregate or apart."""
    from adapters import simpler_variants as sv

    axes = sv.axes()
    assert set(axes) == set(SIMPLERENV_AXES) | set(HARNESS_AXES)
    assert {a for a in axes if axes[a].kind == "physical"} <= set(HARNESS_AXES)
