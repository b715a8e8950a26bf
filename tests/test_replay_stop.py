"""The bench's sequential rule (results/replay_stop.py) on synthetic timings: a verdict
that is clear settles after fewer rounds with the verdict all the rounds would give; one
that straddles the allowed slowdown takes every round up to the cap."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from harness.bench import time_rounds
from policies.base import ChunkBatch
from results.replay import paired_ratios, replay_speed
from results.replay_stop import JudgedPair, StoppingRule

FAST, REF = JudgedPair("fast_dvla", "c-fast", "b-fast"), JudgedPair("bidirectional", "c-ref", "b-ref")


def seconds(ratio: float, spread: float, n: int, seed: int) -> dict[str, list[float]]:
    """Per-round seconds per chunk of a decoder at `ratio` x the reference's, under a
    load that comes and goes between rounds (it cancels in the ratio), and noise `spread`."""
    rng = np.random.default_rng(seed)
    reference = 0.025 * np.exp(rng.normal(0.0, 0.3, n))
    fast = reference * ratio * np.exp(rng.normal(0.0, spread, n))
    return {"fast": fast.tolist(), "ref": reference.tolist()}


def rule(baseline: dict[str, list[float]], max_slowdown: float = 0.10, cap: int = 40) -> StoppingRule:
    rounds = {"b-fast": baseline["fast"], "b-ref": baseline["ref"]}
    return StoppingRule(rounds, (FAST,), REF, max_slowdown, min_rounds=10, cap=cap)


def timed_until_settled(stopping: StoppingRule, candidate: dict[str, list[float]]) -> dict[str, list[float]]:
    """The rounds a bench would keep: one at a time until the rule stops it or the cap."""
    kept: dict[str, list[float]] = {"c-fast": [], "c-ref": []}
    for fast, ref in zip(candidate["fast"], candidate["ref"], strict=True):
        kept["c-fast"].append(fast)
        kept["c-ref"].append(ref)
        if stopping.settled(kept) or len(kept["c-ref"]) == stopping.cap:
            break
    return kept


def gate_verdict(baseline: dict[str, list[float]], kept: dict[str, list[float]], max_slowdown: float = 0.10):
    """The verdict the gate reads from the rounds written (results/replay.py, 95%)."""
    return replay_speed(
        "fast_dvla",
        paired_ratios(baseline["fast"], baseline["ref"]),
        paired_ratios(kept["c-fast"], kept["c-ref"]),
        max_slowdown,
    )


def test_the_looks_and_their_raised_confidence():
    stopping = rule(seconds(0.55, 0.03, 30, 0))
    assert stopping.looks() == [10, 15, 20, 25, 30, 35, 40]
    assert stopping.confidence == pytest.approx(1 - 0.05 / 7)
    fixed = StoppingRule({}, (FAST,), REF, 0.10, min_rounds=30, cap=30)
    assert fixed.looks() == [30] and fixed.confidence == pytest.approx(0.95)


@pytest.mark.parametrize(
    ("name", "slower", "expected"),
    [("unchanged", 1.0, "pass"), ("30% more time per chunk", 1.3, "fail")],
)
def test_a_clear_verdict_settles_early_with_the_verdict_all_rounds_give(name, slower, expected):
    baseline = seconds(0.55, 0.03, 30, seed=1)
    candidate = seconds(0.55 * slower, 0.03, 40, seed=2)
    stopping = rule(baseline)
    kept = timed_until_settled(stopping, candidate)
    used = len(kept["c-ref"])
    assert used == 10, f"{name}: {used} rounds"  # the first look settles it
    everything = {"c-fast": candidate["fast"], "c-ref": candidate["ref"]}
    early, full = gate_verdict(baseline, kept), gate_verdict(baseline, everything)
    assert early.verdict == full.verdict == expected
    assert early.rounds == (30, 10) and full.rounds == (30, 40)
    record = stopping.record(kept)
    assert record["stopped"] == "settled" and record["rounds"] == 10 and record["max_rounds"] == 40
    assert record["verdicts"] == {"fast_dvla": expected}


def test_a_verdict_that_straddles_the_limit_takes_every_round_to_the_cap():
    baseline = seconds(0.55, 0.03, 30, seed=3)
    candidate = seconds(0.55 / 0.9, 0.03, 40, seed=4)  # exactly the allowed slowdown
    stopping = rule(baseline)
    kept = timed_until_settled(stopping, candidate)
    assert len(kept["c-ref"]) == 40
    assert stopping.record(kept)["stopped"] == "cap"


def test_a_noisy_machine_needs_more_rounds_than_a_quiet_one():
    baseline = seconds(0.55, 0.03, 30, seed=5)
    quiet = timed_until_settled(rule(baseline), seconds(0.55 * 1.14, 0.02, 40, seed=6))
    noisy = timed_until_settled(rule(baseline), seconds(0.55 * 1.14, 0.10, 40, seed=6))
    assert len(quiet["c-ref"]) < len(noisy["c-ref"])
    assert gate_verdict(baseline, quiet).verdict == "fail"


def test_a_settled_look_is_always_the_gates_verdict():
    # whatever the rounds, an interval at the raised confidence holds the 95% one: a look
    # that settles never disagrees with the verdict the gate reads from the same rounds
    baseline = seconds(0.55, 0.05, 30, seed=7)
    stopping = rule(baseline, cap=30)
    for seed in range(40):
        slower = 1.0 + 0.01 * (seed % 25)
        kept = timed_until_settled(stopping, seconds(0.55 * slower, 0.05, 30, seed=100 + seed))
        if stopping.record(kept)["stopped"] == "settled":
            assert stopping.record(kept)["verdicts"]["fast_dvla"] == gate_verdict(baseline, kept).verdict


def test_time_rounds_stops_when_the_rule_says_so():
    class Instant:
        def reset(self, episodes):
            pass

        def act(self, observations):
            return ChunkBatch(np.zeros((1, 1, 1)), action_tokens=1)

    policies = [SimpleNamespace(config_id=c, policy=Instant()) for c in ("a", "b")]
    asked: list[int] = []

    def stop(rounds: dict[str, list[float]]) -> bool:
        asked.append(len(rounds["a"]))
        return len(rounds["a"]) == 4

    out = time_rounds(policies, [None] * 3, [np.zeros(2)] * 3, 10, stop=stop)
    assert asked == [1, 2, 3, 4] and len(out.wall["a"]) == len(out.wall["b"]) == len(out.cpu["b"]) == 4
