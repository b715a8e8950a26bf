"""benchmarks/replay_load.py: the figures docs/ci-gate.md explains the load bias with (the
per-pass and per-GFLOP fit, the per-round ratios from wall and CPU time) are computed as
it says, and a condition it does not know is refused before any load starts."""

from __future__ import annotations

import json

import pytest

from benchmarks import replay_load


def test_the_fit_recovers_the_cost_of_a_pass_and_of_a_gflop():
    bench = replay_load
    replay = json.loads((bench.BASELINE / "replay.json").read_text())
    configs = {c["policy"]: c for c in replay["configurations"]}
    per_pass, per_gflop = 2.5, 15.0  # ms: what a loaded machine might cost

    def ms(policy: str) -> float:
        return (
            per_pass * configs[policy]["nfe_per_chunk"] + per_gflop * configs[policy]["flops_per_chunk"] / 1e9
        )

    a, b = bench.pass_flop_fit(ms("fast_dvla"), ms("bidirectional"))
    assert a == pytest.approx(per_pass) and b == pytest.approx(per_gflop)
    # the committed idle bench: mostly per-pass cost for fast_dvla, as the docs say
    a, b = bench.pass_flop_fit(*(1e3 * configs[p]["median_chunk_s"] for p in ("fast_dvla", "bidirectional")))
    share = a * configs["fast_dvla"]["nfe_per_chunk"] / (1e3 * configs["fast_dvla"]["median_chunk_s"])
    assert a == pytest.approx(1.31, abs=0.01) and b == pytest.approx(9.85, abs=0.05) and share > 0.8


def test_ratios_pair_calls_within_a_round_from_wall_and_cpu_time():
    bench = replay_load

    def call(policy: str, wall: float, cpu: float, preempted: int = 0) -> dict:
        return {"policy": policy, "wall": wall, "cpu": cpu, "preempted": preempted}

    rounds = [
        [call("fast_dvla", 0.6, 0.5), call("bidirectional", 1.0, 1.0, 2)],
        [call("fast_dvla", 1.2, 0.5, 4), call("bidirectional", 2.0, 1.0, 2)],  # a busier round: wall x2
        [call("fast_dvla", 0.6, 0.5), call("bidirectional", 1.0, 1.0)],
    ]
    s = bench.summarise(rounds)
    assert s["ratio_wall"] == pytest.approx(0.6) and s["ratio_cpu"] == pytest.approx(0.5)
    assert s["ratio_wall_spread"] == pytest.approx(0.0) and s["rounds"] == 3
    assert s["fast_dvla_wall_over_cpu"] == pytest.approx(2.4 / 1.5)
    assert s["fast_dvla_preempted_per_call"] == pytest.approx(4 / 3)


def test_an_unknown_condition_is_refused_before_any_load(capsys):
    bench = replay_load
    with pytest.raises(SystemExit) as exit_:
        bench.main(["--conditions", "idle,hot", "--json", "/nonexistent/out.json"])
    assert exit_.value.code == 2
    assert "unknown condition(s) hot; valid: idle, busy1, busy2, mem1, mem2" in capsys.readouterr().err
