"""The run summary table: what each speed column means is printed with it, and per-task
speedups appear only with enough episodes to mean something."""

from __future__ import annotations

import io

import pandas as pd
from rich.console import Console

from results.render import MIN_EPISODES_FOR_TASK_SPEEDUP, summary_table
from results.summary import summarize


def _rows(policy: str, n: int, tokens_per_s: float) -> list[dict]:
    return [
        {
            "policy_config_id": policy,
            "policy": policy,
            "task": "reach",
            "task_index": 0,
            "success": True,
            "failure_reason": None,
            "nfe_per_chunk": 12.0,
            "tokens_per_s": tokens_per_s,
            "control_hz": 400.0,
            "loop_hz": 300.0,
            "wall_clock_s": 0.5,
            "started_at": pd.Timestamp("2026-01-01", tz="UTC") + pd.Timedelta(seconds=i),
        }
        for i in range(n)
    ]


def _render(n: int) -> str:
    summary = summarize(pd.DataFrame(_rows("bidirectional", n, 100.0) + _rows("fast_dvla", n, 250.0)))
    out = io.StringIO()
    Console(file=out, width=250).print(summary_table(summary))
    return out.getvalue()


def test_per_task_speedup_needs_enough_episodes_and_all_always_has_one():
    few = _render(3)
    assert few.count("2.50x") == 1  # the ALL row only
    many = _render(MIN_EPISODES_FOR_TASK_SPEEDUP)
    assert many.count("2.50x") == 2  # the task row too


def test_the_table_says_what_control_hz_loop_hz_and_speedup_mean():
    text = _render(3)
    assert "loop Hz" in text and "300" in text
    assert "control Hz: env steps per second of policy time" in text
    assert "speedup vs bidirectional" in text
