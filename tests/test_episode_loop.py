"""The episode loop on a physics-free env: chunks, budgets, success, timing, failures."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from adapters.base import EpisodeSpec
from harness.run.rows import derived
from tests.fakes import ChunkPolicy, CountdownEnv, context, run_one


def _run(env, policy, max_steps=50, replan_every=0):
    return run_one(env, policy, context(max_steps), EpisodeSpec(0), replan_every)


def test_whole_chunk_is_executed_before_replanning():
    env, policy = CountdownEnv(succeed_at=10), ChunkPolicy(chunk=4)
    out = _run(env, policy)
    assert out.success and out.steps == 10
    assert out.chunks == 3  # 4 + 4 + 2 of the third chunk
    executed = [int(a[0]) for a in env.actions]
    assert executed == list(range(10))  # actions in order, none skipped
    assert out.action_tokens_total == 3 * 4 * 2


def test_replan_every_executes_only_a_prefix_of_each_chunk():
    env, policy = CountdownEnv(succeed_at=6), ChunkPolicy(chunk=4)
    out = _run(env, policy, replan_every=2)
    assert out.chunks == 3
    executed = [int(a[0]) for a in env.actions]
    assert executed == [0, 1, 4, 5, 8, 9]  # first two of each chunk


def test_step_budget_ends_an_unsuccessful_episode():
    out = _run(CountdownEnv(succeed_at=None), ChunkPolicy(chunk=3), max_steps=10)
    assert not out.success
    assert out.steps == 10 and out.chunks == 4
    assert out.failure_reason is None


def test_success_stops_mid_chunk():
    env = CountdownEnv(succeed_at=1)
    out = _run(env, ChunkPolicy(chunk=8))
    assert out.success and out.steps == 1 and len(env.actions) == 1


def test_timing_columns_add_up_and_measure_each_side():
    # each side sleeps 0.12 s in all: the margin a sleep may overrun on a busy CPU (parallel tests)
    env, policy = CountdownEnv(succeed_at=12, step_delay=0.01), ChunkPolicy(chunk=4, delay=0.04)
    before = time.perf_counter()
    out = _run(env, policy)
    outside = time.perf_counter() - before
    # The wall clock is a measurement: inside what a clock outside the episode saw, and
    # covering both sides' sleeps; the loop's own time is what is left, never negative.
    assert out.policy_time_s + out.env_time_s <= out.wall_clock_s <= outside
    assert out.wall_clock_s >= 12 * 0.01 + 3 * 0.04
    # Each side carries its own sleeps and not the other's.
    assert out.env_time_s >= 12 * 0.01
    assert out.policy_time_s >= 3 * 0.04
    assert out.env_time_s < 12 * 0.01 + 3 * 0.04
    assert out.policy_time_s < 3 * 0.04 + 12 * 0.01
    overhead = out.wall_clock_s - out.policy_time_s - out.env_time_s
    assert 0 <= overhead < 0.05 * out.wall_clock_s


def test_env_exception_is_recorded_not_raised():
    out = _run(CountdownEnv(succeed_at=None, fail_at=3), ChunkPolicy(chunk=2))
    assert not out.success
    assert out.failure_reason == "RuntimeError: simulator exploded"
    assert "simulator exploded" in out.traceback
    assert out.steps == 2  # the step that raised is not counted


class WrongShapePolicy(ChunkPolicy):
    def act(self, observations):
        batch = super().act(observations)
        batch.actions = np.zeros((1, 4, 3))
        return batch


def test_wrong_action_dimension_is_a_clear_failure():
    out = _run(CountdownEnv(succeed_at=None), WrongShapePolicy())
    assert out.failure_reason is not None
    assert "3-D actions; the action space is 2-D" in out.failure_reason


@pytest.mark.parametrize("chunk", [1, 5])
def test_control_hz_is_steps_over_policy_time(chunk):
    delay = 0.02  # per policy call, so the policy alone sustains chunk / delay steps a second
    out = _run(CountdownEnv(succeed_at=7), ChunkPolicy(chunk=chunk, delay=delay))
    calls = math.ceil(7 / chunk)
    assert out.steps == 7 and out.chunks == calls
    hz = derived(out, "count", chain=False)["control_hz"]
    assert hz == out.steps / out.policy_time_s
    # the sleeps bound it from above; a busy CPU may only lower it
    assert hz <= 7 / (calls * delay)
    assert hz >= 7 / (calls * delay + 1.0)


class _Misbehaving(ChunkPolicy):
    """Acts normally, then on its second chunk does `what`."""

    def __init__(self, what):
        super().__init__(chunk=2)
        self.what = what

    def act(self, observations):
        batch = super().act(observations)  # counts self.calls
        if self.calls == 2:
            if isinstance(self.what, BaseException):
                raise self.what
            batch.actions = np.full_like(np.asarray(batch.actions, dtype=float), self.what)
        return batch


class _Custom(BaseException):
    pass


@pytest.mark.parametrize(
    ("what", "reason"),
    [
        (SystemExit(3), "SystemExit: 3"),
        (_Custom("gone"), "_Custom: gone"),
        (float("nan"), "non-finite action"),
        (float("inf"), "non-finite action"),
        (1e30, "absurd action (1e+30 in magnitude)"),
    ],
)
def test_a_policy_that_exits_or_acts_non_finite_ends_only_its_episode(what, reason):
    out = _run(CountdownEnv(succeed_at=None), _Misbehaving(what), max_steps=20)
    assert not out.success and out.steps == 2 and reason in out.failure_reason


def test_keyboard_interrupt_still_stops_the_run():
    with pytest.raises(KeyboardInterrupt):
        _run(CountdownEnv(succeed_at=None), _Misbehaving(KeyboardInterrupt()), max_steps=20)


def test_the_loop_cost_benchmark_times_each_chunk_length(tmp_path):
    import importlib.util
    import json
    from pathlib import Path

    path = Path(__file__).resolve().parent.parent / "benchmarks" / "loop_cost.py"
    spec = importlib.util.spec_from_file_location("loop_cost", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    assert module.main(["--episodes", "2", "--steps", "30", "--json", str(tmp_path / "cost.json")]) == 0
    result = json.loads((tmp_path / "cost.json").read_text())
    us = result["us_per_step"]
    assert set(us) == {"1000", "8", "1"} and all(v > 0 for v in us.values())
    assert us["1"] > us["1000"]  # a call every step costs more than a step alone
