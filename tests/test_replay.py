"""The replay benchmark: its verdict (pass / fail / inconclusive) on synthetic timings of
known distributions, the gate judging speed on it when both runs were benched, `bench`
on a tiny real run, and bad input refused with exit 2."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from results.replay import (
    REPLAY,
    REPLAY_VERSION,
    ReplayFileError,
    ReplaySpeed,
    bootstrap_median_interval,
    load_replay,
    replay_speed,
)
from tests.test_gate import with_reference, write_run

pytestmark = pytest.mark.metaworld  # these tests run Meta-World episodes


def ratios(median: float, spread: float, n: int, seed: int) -> np.ndarray:
    """Per-round paired ratios: lognormal around `median`, relative spread `spread`."""
    return median * np.exp(np.random.default_rng(seed).normal(0.0, spread, n))


# ---- the verdict on known distributions ------------------------------------------------


def test_verdict_boundaries():
    def speed(low: float, high: float) -> ReplaySpeed:
        return ReplaySpeed("p", 0.5, 0.5, low, high, 0.10, (30, 30))

    assert speed(-0.20, -0.11).verdict == "fail"  # the whole interval beyond -10%
    assert speed(-0.12, -0.05).verdict == "inconclusive"  # straddles it
    assert speed(-0.09, 0.02).verdict == "pass"
    assert speed(-0.10, 0.0).verdict == "pass"  # exactly the allowed slowdown is allowed


def test_unchanged_timings_pass_and_the_interval_holds_no_change():
    base, cand = ratios(0.55, 0.04, 30, seed=1), ratios(0.55, 0.04, 30, seed=2)
    s = replay_speed("fast_dvla", base, cand, 0.10)
    assert s.verdict == "pass"
    assert s.low < 0.0 < s.high and s.high - s.low < 0.06  # 30 rounds of 4% noise: a few %
    assert s.rounds == (30, 30)


def test_a_clear_slowdown_fails():
    # 30% more time per chunk relative to the reference: speed -23%, beyond 10% whatever the noise
    base, cand = ratios(0.55, 0.04, 30, seed=1), ratios(0.55 * 1.3, 0.04, 30, seed=2)
    s = replay_speed("fast_dvla", base, cand, 0.10)
    assert s.verdict == "fail"
    assert s.high < -0.10 and s.low < s.change < s.high
    assert s.change == pytest.approx(1 / 1.3 - 1, abs=0.03)


def test_a_slowdown_near_the_bound_on_a_noisy_machine_is_inconclusive():
    # speed -10% on average, measured with 20% noise over 10 rounds: the interval straddles -10%
    base, cand = ratios(0.55, 0.20, 10, seed=3), ratios(0.55 / 0.9, 0.20, 10, seed=4)
    s = replay_speed("fast_dvla", base, cand, 0.10)
    assert s.verdict == "inconclusive", s
    assert s.low < -0.10 < s.high


def test_the_same_slowdown_measured_precisely_is_decided():
    # 15% slower with 2% noise and 40 rounds: the interval is narrow enough to fail at 10%
    base, cand = ratios(0.55, 0.02, 40, seed=5), ratios(0.55 / 0.85, 0.02, 40, seed=6)
    assert replay_speed("fast_dvla", base, cand, 0.10).verdict == "fail"
    assert replay_speed("fast_dvla", base, cand, 0.25).verdict == "pass"


def test_bootstrap_is_seeded_and_an_improvement_never_fails():
    base, cand = ratios(0.55, 0.05, 20, seed=7), ratios(0.40, 0.05, 20, seed=8)
    first, again = replay_speed("f", base, cand, 0.0), replay_speed("f", base, cand, 0.0)
    assert (first.low, first.high) == (again.low, again.high)
    assert first.verdict == "pass" and first.change > 0.2
    low, high = bootstrap_median_interval([1.0, 2.0, 3.0, 4.0, 5.0])
    assert 1.0 <= low <= 3.0 <= high <= 5.0


# ---- the gate on benched runs -----------------------------------------------------------


def config_ids(run: Path) -> dict[str, str]:
    import pandas as pd

    df = pd.read_parquet(run / "episodes.parquet")
    return dict(zip(df["policy"], df["policy_config_id"], strict=False))


def bench_file(run: Path, fast: np.ndarray, reference: np.ndarray, **extra) -> Path:
    """A replay.json of `run` with per-round seconds per chunk of fast_dvla and bidirectional."""
    ids = config_ids(run)

    def entry(policy: str, rounds: np.ndarray) -> dict:
        return {
            "policy": policy,
            "policy_config_id": ids[policy],
            "round_chunk_s": [float(v) for v in rounds],
        }

    data = {
        "replay_version": REPLAY_VERSION,
        "rounds": len(fast),
        "torch_threads": 1,
        "observations": {"sha256": "abc", "count": 12},
        "configurations": [entry("fast_dvla", fast), entry("bidirectional", reference)],
    } | extra
    (run / REPLAY).write_text(json.dumps(data))
    return run


def benched(
    tmp_path: Path, name: str, closed_loop: float, replay_ratio: float, spread: float, seed: int
) -> Path:
    """A run folder whose fast_dvla ran at `closed_loop` x the reference's tokens/s in its
    episodes and `replay_ratio` x its time per chunk in the bench."""
    run = write_run(tmp_path / name, with_reference(1000.0 * closed_loop, 1000.0), calibration=5000.0)
    reference = 0.1 * np.exp(np.random.default_rng(seed).normal(0, 0.3, 30))  # a load that comes and goes
    return bench_file(run, reference * ratios(replay_ratio, spread, 30, seed + 100), reference)


def test_gate_fails_on_a_replay_slowdown_the_closed_loop_ratio_missed(cli, tmp_path):
    base = benched(tmp_path, "base", 2.0, 0.50, 0.03, seed=1)
    cand = benched(tmp_path, "cand", 2.0, 0.50 * 1.4, 0.03, seed=2)  # 40% more time per chunk
    code, out, err = cli("gate", "--baseline", str(base), "--candidate", str(cand), "--max-slowdown", "0.10")
    assert code == 1, out + err
    assert "fast_dvla: replay speed relative to the reference -2" in err  # about -29%
    assert "replay vs ref." in out and "judged on the replay benchmark" in out


def test_gate_does_not_fail_on_the_closed_loop_ratio_when_replay_holds(cli, tmp_path):
    base = benched(tmp_path, "base", 2.0, 0.50, 0.03, seed=1)
    cand = benched(tmp_path, "cand", 1.0, 0.50, 0.03, seed=2)  # episodes read -50%: a noisy run
    code, out, err = cli("gate", "--baseline", str(base), "--candidate", str(cand), "--max-slowdown", "0.10")
    assert code == 0, out + err
    assert "-50.0%" in out  # the closed-loop figure is still reported
    assert "gate passed" in out
    # without the candidate's bench, the same runs fail on the closed-loop ratio, as before
    (cand / REPLAY).unlink()
    code, out, err = cli("gate", "--baseline", str(base), "--candidate", str(cand), "--max-slowdown", "0.10")
    assert code == 1 and "tokens/s relative to the reference -50.0%" in err
    assert "only one run was benched (not the candidate)" in out


def test_gate_says_inconclusive_and_passes_when_the_interval_straddles(cli, tmp_path):
    base = benched(tmp_path, "base", 2.0, 0.50, 0.25, seed=3)
    cand = benched(tmp_path, "cand", 2.0, 0.50 / 0.9, 0.25, seed=4)
    code, out, err = cli("gate", "--baseline", str(base), "--candidate", str(cand), "--max-slowdown", "0.10")
    assert code == 0, out + err
    assert "replay speed inconclusive" in out and "gate passed" in out
    assert "speed inconclusive for fast_dvla (warning above)" in out


def with_work(run: Path, fast_flops: float | None, reference_flops: float = 9.0e8) -> Path:
    """`run`'s replay.json with each configuration's work per chunk counted at the dispatcher
    (and by the module hooks, which saw all of it only at the baseline's figure)."""
    data = json.loads((run / REPLAY).read_text())
    for c in data["configurations"]:
        flops = fast_flops if c["policy"] == "fast_dvla" else reference_flops
        c["flops_per_chunk"] = flops
        c["module_flops_per_chunk"] = 2.0e8 if c["policy"] == "fast_dvla" else flops
    (run / REPLAY).write_text(json.dumps(data))
    return run


def test_work_the_module_hooks_miss_fails_the_gate_on_the_replay_count(cli, tmp_path):
    # a raw torch.matmul per pass, outside any module: the episodes' counted work (module
    # hooks) and NFE are unchanged, the speed holds, and only the dispatcher count rises
    base = with_work(benched(tmp_path, "base", 2.0, 0.50, 0.03, seed=1), 2.0e8)
    cand = with_work(benched(tmp_path, "cand", 2.0, 0.50, 0.03, seed=2), 2.32e8)
    code, out, err = cli("gate", "--baseline", str(base), "--candidate", str(cand))
    assert code == 1, out + err
    assert "fast_dvla: counted work of every torch product (replay) 0.2 -> 0.232 GFLOP/chunk (+16.00%)" in err
    assert "FAIL work" in out and "13.8% of its bench's products ran outside the counted modules" in " ".join(
        out.split()
    )
    code, out, err = cli("gate", "--baseline", str(base), "--candidate", str(cand), "--allow-work-increase")
    assert code == 0, out + err
    same = with_work(benched(tmp_path, "same", 2.0, 0.50, 0.03, seed=3), 2.0e8)
    code, out, err = cli("gate", "--baseline", str(base), "--candidate", str(same))
    assert code == 0 and "outside the counted modules" not in out, out + err
    older = benched(tmp_path, "older", 2.0, 0.50, 0.03, seed=4)  # a bench from before the count
    code, out, err = cli("gate", "--baseline", str(older), "--candidate", str(cand))
    assert code == 0, out + err
    assert "counted work of every torch product not compared for fast_dvla, bidirectional" in " ".join(
        out.split()
    )


def test_inconclusive_fails_the_gate_when_asked(cli, tmp_path):
    base = benched(tmp_path, "base", 2.0, 0.50, 0.25, seed=3)
    cand = benched(tmp_path, "cand", 2.0, 0.50 / 0.9, 0.25, seed=4)
    code, out, err = cli("gate", "--baseline", str(base), "--candidate", str(cand), "--inconclusive", "fail")
    assert code == 1, out + err
    assert "fast_dvla: replay speed inconclusive, failed as asked (--inconclusive fail)" in err
    code, out, err = cli("gate", "--baseline", str(base), "--candidate", str(cand), "--inconclusive", "pass")
    assert code == 0 and "replay speed inconclusive" in out
    code, _, err = cli("gate", "--baseline", str(base), "--candidate", str(cand), "--inconclusive", "maybe")
    assert code == 2 and "invalid choice: 'maybe'" in err
    clear = benched(tmp_path, "clear", 2.0, 0.50, 0.03, seed=5)
    code, out, err = cli(
        "gate", "--baseline", str(clear), "--candidate", str(clear), "--inconclusive", "fail"
    )
    assert code == 0, out + err  # a settled pass stays a pass


def test_the_verdict_says_which_figure_decided_and_how_far_to_trust_it(cli, tmp_path):
    base = benched(tmp_path, "base", 2.0, 0.50, 0.03, seed=1)
    cand = write_run(tmp_path / "cand", with_reference(1000.0, 1000.0), calibration=5000.0, end=2000.0)
    # the reference about twice as slow as in the baseline's bench: a busy machine
    reference = 0.2 * np.exp(np.random.default_rng(9).normal(0, 0.05, 30))
    bench_file(
        cand,
        reference * ratios(0.50, 0.03, 30, 109),
        reference,
        sequential={"stopped": "settled", "rounds": 30},
        max_rounds=40,
    )
    code, out, err = cli("gate", "--baseline", str(base), "--candidate", str(cand))
    text = " ".join(out.split())
    assert code == 0, out + err
    from harness.commands.gate import render
    from results.gate import gate_runs
    from results.runs import load_run

    table = render(gate_runs(load_run(base), load_run(cand)), "t")
    assert "tokens/s vs ref. (closed loop, not judged)" in [c.header for c in table.columns]
    # the closed-loop run's drift is a note about figures that decided nothing, not a warning
    assert "warning" not in text
    assert "closed-loop speed figures unreliable: the calibration moved -60%" in text
    assert "not used for the verdict: the replay judged speed" in text
    assert "verdict: fast_dvla: speed pass on the replay, " in text
    assert re.search(
        r"30 rounds \(settled early, at most 40\); figure doubtful: the reference decoded [12]\.\d\dx slower",
        text,
    )


def test_benches_at_different_thread_counts_are_not_compared(cli, tmp_path):
    base = benched(tmp_path, "base", 2.0, 0.50, 0.03, seed=1)
    cand = benched(tmp_path, "cand", 2.0, 0.50 * 1.4, 0.03, seed=2)
    data = json.loads((cand / REPLAY).read_text()) | {"torch_threads": 2}
    (cand / REPLAY).write_text(json.dumps(data))
    code, out, _err = cli("gate", "--baseline", str(base), "--candidate", str(cand), "--max-slowdown", "0.10")
    assert code == 0 and "replay not comparable: torch threads differ" in out


@pytest.mark.parametrize(
    "text, message",
    [
        (
            '{"replay_version": 1, "configurations": [{"policy_config_id": "x", "round_chunk_s": [NaN, 1]}]}',
            "JSON",
        ),
        ('{"replay_version": 99, "configurations": []}', "replay_version 99"),
        (
            '{"replay_version": 1, "configurations": [{"policy_config_id": "x", "round_chunk_s": [1]}]}',
            "round_chunk_s",
        ),
        ("not json", "JSON"),
        (
            '{"replay_version": 1, "configurations": [{"policy_config_id": "x", "round_chunk_s": [1, 1], '
            '"round_cpu_chunk_s": [1]}]}',
            "round_cpu_chunk_s",
        ),
        (
            '{"replay_version": 1, "configurations": [{"policy_config_id": "x", "round_chunk_s": [1, 1], '
            '"flops_per_chunk": -5}]}',
            "flops_per_chunk",
        ),
        (
            '{"replay_version": 1, "sequential": [], "configurations": [{"policy_config_id": "x", '
            '"round_chunk_s": [1, 1]}]}',
            "sequential",
        ),
    ],
)
def test_a_broken_replay_file_exits_2_naming_it(cli, tmp_path, text, message):
    base = benched(tmp_path, "base", 2.0, 0.50, 0.03, seed=1)
    cand = benched(tmp_path, "cand", 2.0, 0.50, 0.03, seed=2)
    (cand / REPLAY).write_text(text)
    with pytest.raises(ReplayFileError, match=message):
        load_replay(cand)
    code, _out, err = cli("gate", "--baseline", str(base), "--candidate", str(cand))
    assert code == 2 and "replay.json" in err and message in err


# ---- bench on a real run ------------------------------------------------------------------


def test_bench_bad_input_exits_2_and_writes_nothing(cli, tmp_path):
    code, _, err = cli("bench", str(tmp_path / "nowhere"))
    assert code == 2 and "not a run folder" in err
    run = write_run(tmp_path / "run", with_reference(2000.0, 1000.0))
    code, _, err = cli("bench", str(run), "--rounds", "1")
    assert code == 2 and "at least 2" in err
    code, _, err = cli("bench", str(run), "--observations", str(tmp_path / "missing"))
    assert code == 2 and "--observations" in err and "does not exist" in err
    bogus = tmp_path / "bogus.npz"
    bogus.write_bytes(b"not a zip")
    code, _, err = cli("bench", str(run), "--observations", str(bogus))
    assert code == 2 and "not a recorded-observations file" in err
    assert not (run / REPLAY).exists()


def test_bench_help_teaches(cli):
    code, out, _ = cli("bench", "--help")
    assert code == 0
    assert "--rounds" in out and "--observations" in out and "examples:" in out
    assert "bootstrap" in out and "dvla-harness gate" in out


def test_bench_on_a_tiny_run_writes_figures_the_gate_uses(cli, tmp_path, one_torch_thread, monkeypatch):
    pytest.importorskip("metaworld")
    run = tmp_path / "run"
    policies = ("--policy", "scripted", "--policy", "fast_dvla", "--policy", "bidirectional")
    tiny = ("--suite", "metaworld/mt10", "--tasks", "drawer-close-v3", "--episodes-per-task", "1")
    code, _, err = cli("run", *tiny, *policies, "--out", str(run), "--quiet")
    assert code == 0, err
    code, _, err = cli("bench", str(run), "--record-from", "nobody", "--quiet")
    assert code == 2 and "--record-from 'nobody'" in err and "bidirectional" in err
    assert not (run / REPLAY).exists()
    code, out, err = cli("bench", str(run), "--rounds", "3", "--observations-per-task", "2", "--quiet")
    assert code == 0, err
    text = (run / REPLAY).read_text()
    data = json.loads(text, parse_constant=lambda c: pytest.fail(f"{c} in replay.json"))
    assert load_replay(run) == data
    timed = {c["policy"]: c for c in data["configurations"]}
    assert set(timed) == {"fast_dvla", "bidirectional"}  # scripted decodes no tokens
    assert data["not_timed"][0]["policy"] == "scripted"
    for c in timed.values():
        assert len(c["round_chunk_s"]) == 3 and c["min_chunk_s"] <= c["median_chunk_s"]
        low, high = c["median_chunk_s_interval"]
        assert low <= c["median_chunk_s"] <= high and c["action_tokens_per_chunk"] > 0
    assert timed["bidirectional"]["nfe_per_chunk"] > timed["fast_dvla"]["nfe_per_chunk"]
    assert {c["policy_params"]["checkpoint"] for c in timed.values()} == {"metaworld-mt10"}  # no machine path
    assert data["observations"]["count"] == 2 and "replay:" in out
    assert data["sequential"] is None and data["rounds"] == 3  # no baseline bench: fixed
    assert timed["fast_dvla"]["flops_per_chunk"] == timed["fast_dvla"]["module_flops_per_chunk"] > 0
    assert len(timed["bidirectional"]["round_cpu_chunk_s"]) == 3
    # a copy benched on the first's observations decodes the same set, and the gate judges on
    # it; with the first's bench to judge against, the rounds stop once the verdict settles
    other = tmp_path / "other"
    shutil.copytree(run, other, ignore=shutil.ignore_patterns(REPLAY, "replay_observations.npz"))
    code, out, err = cli(
        "bench", str(other), "--rounds", "5", "--min-rounds", "2", "--max-slowdown", "0.9",
        "--observations", str(run), "--quiet",
    )  # fmt: skip
    assert code == 0, err
    again = json.loads((other / REPLAY).read_text())
    assert again["observations"]["sha256"] == data["observations"]["sha256"]
    assert again["sequential"]["stopped"] == "settled" and again["rounds"] == 2 < again["max_rounds"] == 5
    assert "rounds: 2 of at most 5: settled against the baseline bench" in out
    code, out, err = cli("gate", "--baseline", str(run), "--candidate", str(other), "--max-slowdown", "0.5")
    assert code == 0, out + err
    assert "judged on the replay benchmark" in out and "decoded different" not in out
    # a raw torch.matmul in the decoder's step, outside any module: the bench counts it at
    # the dispatcher, and the gate fails on it although NFE and the episodes' work are the same
    from policies.dvla import fast_dvla
    from tests.test_gate_stability import load_benchmark

    monkeypatch.setattr(
        fast_dvla, "decode_fast_dvla", load_benchmark().with_raw_product(fast_dvla.decode_fast_dvla)
    )
    code, _, err = cli("bench", str(other), "--rounds", "2", "--observations", str(run), "--quiet")
    assert code == 0, err
    code, out, err = cli("gate", "--baseline", str(run), "--candidate", str(other), "--max-slowdown", "0.9")
    assert code == 1, out + err
    assert "fast_dvla: counted work of every torch product (replay)" in err
    assert "NFE/chunk" not in err and "counted work 0" not in err  # only the dispatcher saw it


def test_a_policy_that_writes_into_its_observation_leaves_the_recorded_set_alone():
    from types import SimpleNamespace

    from harness.bench import Recorded, time_rounds, warm_up_pass
    from policies.base import ChunkBatch

    class Scribbler:  # as the Meta-World scripted expert does to the array it is handed
        def reset(self, episodes):
            pass

        def act(self, observations):
            observations[0] += 1.0
            return ChunkBatch(np.zeros((1, 1, 1)), action_tokens=1)

    recorded = Recorded("s", [{"task": "t"}] * 2, [np.zeros(3), np.ones(3)])
    digest = recorded.digest()
    run = SimpleNamespace(config_id="c", policy=Scribbler())
    assert warm_up_pass(run.policy, [None, None], recorded.observations).action_tokens == 2
    rounds = time_rounds([run], [None, None], recorded.observations, 3)
    assert len(rounds.wall["c"]) == len(rounds.cpu["c"]) == 3 and recorded.digest() == digest
    assert recorded.observations[1].tolist() == [1.0, 1.0, 1.0]


def test_the_committed_baseline_is_benched_on_observations_that_load():
    from harness.bench import load_observations
    from tests.test_gate import BASELINE

    data = load_replay(BASELINE)
    recorded = load_observations(BASELINE / "replay_observations.npz")
    assert data["observations"]["sha256"] == recorded.digest()  # the set the rounds decoded
    assert data["observations"]["count"] == len(recorded.observations) >= 3
    assert {c["policy"] for c in data["configurations"]} == {"fast_dvla", "bidirectional"}
    assert data["torch_threads"] == 1 and data["rounds"] >= 20
    size = sum(p.stat().st_size for p in BASELINE.iterdir())
    assert size < 200_000, f"the baseline folder grew to {size} bytes"


def _strings(value):
    if isinstance(value, dict):
        return [s for v in value.values() for s in _strings(v)]
    if isinstance(value, list):
        return [s for v in value for s in _strings(v)]
    return [value] if isinstance(value, str) else []


def test_the_committed_replay_file_names_no_machine_path():
    from tests.test_gate import BASELINE

    data = load_replay(BASELINE)
    assert not [s for s in _strings(data) if Path(s).is_absolute()]
    assert {c["policy_params"]["checkpoint"] for c in data["configurations"]} == {"metaworld-mt10"}


def test_bench_records_a_shipped_checkpoint_by_its_set_name():
    from types import SimpleNamespace

    from harness.bench import portable_params
    from policies.dvla.policy import shipped
    from policies.registry import get_policy, params_json, parse_params, portable_checkpoint

    fast = get_policy("fast_dvla")
    run = SimpleNamespace(spec=fast, params_json=params_json(parse_params(fast, {})))
    assert json.loads(run.params_json)["checkpoint"] == shipped("fast_dvla")  # an absolute path
    assert portable_params(run)["checkpoint"] == "metaworld-mt10"
    # the set name must give back the same file for that policy, else the package path
    assert portable_checkpoint(get_policy("bidirectional"), shipped("fast_dvla")) == (
        "policies/checkpoints/metaworld-mt10-fast_dvla.safetensors"
    )
    assert portable_checkpoint(fast, "/data/mine.safetensors") == "/data/mine.safetensors"


def test_replay_files_are_the_harness_own_so_overwrite_may_replace_them(tmp_path):
    from results.store import RunDir

    run = write_run(tmp_path / "run", with_reference(2000.0, 1000.0))
    (run / REPLAY).write_text("{}")
    (run / "replay_observations.npz").write_bytes(b"")
    assert RunDir(run).foreign_files() == []
    RunDir(run).remove_recorded()
    assert not (run / REPLAY).exists() and not (run / "replay_observations.npz").exists()
