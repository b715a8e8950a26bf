"""Aggregation against hand-computed values."""

from __future__ import annotations

import math

import pandas as pd
import pytest

from results.summary import summarize, wilson_interval


@pytest.mark.parametrize(
    ("k", "n", "low", "high"),
    [(8, 10, 0.4902, 0.9433), (0, 5, 0.0, 0.4345), (5, 5, 0.5655, 1.0), (50, 100, 0.4038, 0.5962)],
)
def test_wilson_interval_matches_hand_computation(k, n, low, high):
    lo, hi = wilson_interval(k, n)
    assert lo == pytest.approx(low, abs=1e-4) and hi == pytest.approx(high, abs=1e-4)


def test_wilson_interval_of_nothing_is_undefined():
    assert all(math.isnan(v) for v in wilson_interval(0, 0))


def test_summary_per_task_and_overall():
    rows = []
    for task, idx, successes in (("a", 0, [1, 1, 0, 1]), ("b", 1, [0, 0])):
        for i, s in enumerate(successes):
            rows.append(
                {
                    "policy_config_id": "c1",
                    "policy": "p",
                    "task": task,
                    "task_index": idx,
                    "success": bool(s),
                    "failure_reason": None if i else "boom" if task == "b" else None,
                    "nfe_per_chunk": 12.0,
                    "tokens_per_s": 100.0 * (i + 1),
                    "control_hz": 10.0,
                    "wall_clock_s": 2.0,
                }
            )
    summary = summarize(pd.DataFrame(rows)).set_index("task")
    assert summary.loc["a", "success_rate"] == 0.75 and summary.loc["a", "episodes"] == 4
    assert summary.loc["b", "successes"] == 0 and summary.loc["b", "failures"] == 1
    assert summary.loc["ALL", "success_rate"] == pytest.approx(3 / 6)
    assert summary.loc["ALL", "success_low"] == pytest.approx(wilson_interval(3, 6)[0])
    assert summary.loc["ALL", "tokens_per_s"] == pytest.approx((100 + 200 + 300 + 400 + 100 + 200) / 6)
