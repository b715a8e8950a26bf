"""Starved episodes: the policy's CPU time beside its wall time, per episode, and what a
run with starved episodes says (harness/episode/cpu_time.py, the manifest, `run`, `show`).

A policy that waits (time.sleep) inside its call is what starvation looks like to the
measurement: wall time passes, the thread's CPU time does not. A policy that has its
core all the time is simulated exactly by timing the loop's wall clock with the thread's
CPU clock (a machine with nothing else to run), so that test holds on a loaded machine.
"""

from __future__ import annotations

import copy
import time
from types import SimpleNamespace

import pandas as pd
import pyarrow.parquet as pq
import pytest

import harness.episode.loop as loop_module
import harness.episode.timed as timed_module
import harness.run.manifest as manifest_module
from harness.episode.cpu_time import MIN_JUDGED_POLICY_TIME_S, STARVED_FACTOR, cpu_clock, is_starved
from harness.episode.timed import ServedTotals
from harness.run.manifest import record_end_calibration
from harness.run.runner import run
from results import schema
from results.runs import load_run, speed_warning
from results.store import RunDir, read_table
from tests.fakes import ChunkPolicy, CountdownEnv, context, fake_resolved, run_one
from tests.test_batched import BatchPolicy, batched
from tests.test_leaderboard import BIDI, MANIFEST, episodes, write_run


class SpinPolicy(ChunkPolicy):
    """CPU-bound: each call spins until its thread has used `cpu_s` of CPU time."""

    def __init__(self, cpu_s: float = 0.02):
        super().__init__(chunk=2)
        self.cpu_s = cpu_s

    def act(self, observations):
        end = time.thread_time() + self.cpu_s
        while time.thread_time() < end:
            pass
        return super().act(observations)


def test_the_rule_judges_only_episodes_with_enough_policy_time_and_a_cpu_time():
    assert is_starved(1.0, None) is None  # not measured (remote, GPU)
    assert is_starved(MIN_JUDGED_POLICY_TIME_S / 2, 0.0) is None  # too short to judge
    assert is_starved(1.0, 1.0 / STARVED_FACTOR + 0.01) is False
    assert is_starved(1.0, 1.0 / STARVED_FACTOR - 0.01) is True
    assert cpu_clock(SimpleNamespace(device="cuda")) is None  # waits for kernels, not a core
    assert cpu_clock(SimpleNamespace(device="cpu")) is not None
    torch = pytest.importorskip("torch")
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        assert cpu_clock(None) is time.thread_time  # the whole pass runs in this thread
        torch.set_num_threads(2)
        assert cpu_clock(None) is time.process_time  # an intra-op pool works beside it
    finally:
        torch.set_num_threads(threads)


def test_a_policy_that_waits_for_its_core_is_starved_and_the_run_unreliable(tmp_path):
    policy = ChunkPolicy(chunk=2, delay=0.02)  # 5 calls an episode: 0.1 s of waiting
    run(fake_resolved(policy, episodes=2, succeed_at=10), tmp_path / "r")
    rows = RunDir(tmp_path / "r").read_episodes()
    assert (rows["policy_time_s"] >= 0.1).all()
    assert (rows["policy_cpu_time_s"] < rows["policy_time_s"] / 5).all()
    assert rows["starved"].tolist() == [True, True]
    manifest = RunDir(tmp_path / "r").read_manifest()
    starvation = manifest["starvation"]
    assert starvation["starved_episodes"] == 2 and starvation["judged_episodes"] == 2
    assert starvation["factor"] == STARVED_FACTOR and starvation["worst_ratio"] > 5
    assert manifest["speed_reliable"] is False
    assert "2 of 2 episodes judged were starved" in manifest["speed_warning"]
    assert rows["speed_reliable"].tolist() == [False, False]  # the rows carry the verdict
    assert "starved" in load_run(tmp_path / "r").speed_warning  # what leaderboard and gate print


def test_a_cpu_bound_policy_with_its_core_is_not_flagged(monkeypatch, tmp_path):
    # Real clocks: the CPU time is the policy's work (a loaded machine may stretch the wall).
    policy = SpinPolicy(cpu_s=0.02)
    out = run_one(CountdownEnv(succeed_at=8), policy, context(), spec(0))
    assert 4 * 0.02 <= out.policy_cpu_time_s <= out.policy_time_s + 1e-3
    # No load: the wall clock advances only while the thread runs (and the calibration holds).
    monkeypatch.setattr(loop_module, "clock", time.thread_time)
    monkeypatch.setattr(timed_module, "clock", time.thread_time)
    monkeypatch.setattr(manifest_module, "measure_calibration", lambda: {"passes_per_s": 10_000.0})
    run(fake_resolved(SpinPolicy(cpu_s=0.02), episodes=2, succeed_at=8), tmp_path / "r")
    rows = RunDir(tmp_path / "r").read_episodes()
    assert (rows["policy_time_s"] >= MIN_JUDGED_POLICY_TIME_S).all()  # judged
    assert rows["starved"].tolist() == [False, False]
    manifest = RunDir(tmp_path / "r").read_manifest()
    assert manifest["starvation"]["starved_episodes"] == 0
    assert manifest["starvation"]["judged_episodes"] == 2
    assert manifest.get("speed_reliable") in (True, None)  # True when calibrated (torch loaded)
    assert speed_warning(manifest) == ""


class SpinningBatchPolicy(BatchPolicy):
    """A batching policy that works 2 ms on its core in every call."""

    def act_batch(self, episodes, observations):
        end = time.thread_time() + 0.002
        while time.thread_time() < end:
            pass
        return super().act_batch(episodes, observations)


def test_batched_episodes_share_their_calls_cpu_time_and_are_judged_alike(monkeypatch):
    policy = BatchPolicy(chunk=3, delay=0.02)  # waits inside every call
    out, _, _ = batched(policy, episodes=4, k=2)
    for _, o in out:
        assert o.policy_cpu_time_s is not None and o.policy_cpu_time_s < o.policy_time_s / 3
    assert any(is_starved(o.policy_time_s, o.policy_cpu_time_s) for _, o in out)
    # with its core all the time (wall = the thread's CPU clock) no slot is starved; each
    # call works 2 ms on its core, so the clocks compare milliseconds, not the loop's
    # sub-millisecond bookkeeping between the two reads (0.1 ms apart on a busy machine)
    monkeypatch.setattr(loop_module, "clock", time.thread_time)
    monkeypatch.setattr(timed_module, "clock", time.thread_time)
    out, _, _ = batched(SpinningBatchPolicy(chunk=3), episodes=4, k=2)
    for _, o in out:
        assert o.policy_cpu_time_s == pytest.approx(o.policy_time_s, rel=0.05, abs=1e-4)
        assert not is_starved(o.policy_time_s, o.policy_cpu_time_s)


def test_run_prints_the_warning_and_show_repeats_it(cli, monkeypatch, tmp_path):
    import harness.config

    monkeypatch.setattr(
        harness.config, "resolve", lambda _config: fake_resolved(ChunkPolicy(delay=0.02), succeed_at=12)
    )
    code, _, err = cli("run", "--out", str(tmp_path / "r"), "--quiet")
    assert code == 0, err
    (line,) = [ln for ln in err.splitlines() if "unreliable" in ln]
    assert (
        "speed figures of this run are unreliable" in line and "3 of 3 episodes judged were starved" in line
    )
    code, out, _ = cli("show", str(tmp_path / "r"))
    assert code == 0 and "episodes judged were starved" in out


def spec(index: int):
    from adapters.base import EpisodeSpec

    return EpisodeSpec(index=index, seed=index)


def rows(starved: list[bool | None], ratio: float = 2.0) -> pd.DataFrame:
    return pd.DataFrame(
        {
            "policy_time_s": [0.2] * len(starved),
            "policy_cpu_time_s": [0.2 / ratio if s else 0.2 for s in starved],
            "starved": pd.array(starved, dtype="boolean"),
        }
    )


def calibrated() -> dict:
    return copy.deepcopy(MANIFEST) | {
        "calibration": {"workload": {"version": 1}, "start": {"passes_per_s": 10_000.0}}
    }


@pytest.fixture
def end_calibration(monkeypatch):
    """The end-of-run calibration readings, in order (the test appends them)."""
    ends: list[float] = []
    monkeypatch.setattr(manifest_module, "measure_calibration", lambda: {"passes_per_s": ends.pop(0)})
    return ends


def test_the_verdict_combines_drift_and_starvation(end_calibration):
    end_calibration += [10_000.0, 5_000.0, 10_000.0]
    m = calibrated()
    record_end_calibration(m, "finished", rows([False, None, True], ratio=3.0))
    assert m["starvation"]["starved_episodes"] == 1 and m["starvation"]["judged_episodes"] == 2
    assert m["starvation"]["worst_ratio"] == pytest.approx(3.0)
    assert m["speed_reliable"] is False and "calibration moved" not in m["speed_warning"]
    assert "1 of 2 episodes judged were starved" in m["speed_warning"]
    m = calibrated()  # drift and starvation: both reasons, once each
    record_end_calibration(m, "finished", rows([True]))
    assert m["speed_warning"].count("calibration moved -50%") == 1 and "1 of 1 episodes" in m["speed_warning"]
    m = calibrated()  # neither: reliable
    record_end_calibration(m, "finished", rows([False, False]))
    assert m["speed_reliable"] is True and "speed_warning" not in m


def test_a_run_without_calibration_gets_a_verdict_only_when_starved(end_calibration):
    m = copy.deepcopy(MANIFEST)  # no torch policy: calibration skipped
    record_end_calibration(m, "finished", rows([True]))
    assert m["speed_reliable"] is False
    # resumed, the starved row re-run (--retry-failed) clean: the old verdict goes
    record_end_calibration(m, "finished", rows([False]))
    assert "speed_reliable" not in m and "speed_warning" not in m and speed_warning(m) == ""
    record_end_calibration(m, "interrupted", rows([True]))  # an interrupt is not judged
    assert "speed_reliable" not in m


def test_an_older_manifest_with_starved_episodes_but_no_verdict_is_judged_from_them(tmp_path):
    m = copy.deepcopy(MANIFEST) | {
        "starvation": {"starved_episodes": 2, "judged_episodes": 9, "factor": 1.25, "worst_ratio": 2.5}
    }
    assert "2 of 9 episodes judged were starved" in speed_warning(m) and "worst 2.50x" in speed_warning(m)
    path = write_run(tmp_path / "r", episodes("bidirectional", BIDI, "bidi000001", [1]), m)
    assert "starved" in load_run(path).speed_warning


def test_a_version_3_table_reads_without_cpu_time_as_nulls(tmp_path):
    run(fake_resolved(ChunkPolicy(), episodes=1), tmp_path / "r")
    full = pq.read_table(tmp_path / "r" / "episodes.parquet")
    assert full.schema.metadata[schema.SCHEMA_VERSION_KEY] == b"5"
    old = full.drop_columns(["policy_cpu_time_s", "starved"]).replace_schema_metadata(
        {schema.SCHEMA_VERSION_KEY: b"3"}
    )
    pq.write_table(old, tmp_path / "v3.parquet")
    read = read_table(tmp_path / "v3.parquet")
    assert read.column_names == list(schema.COLUMN_NAMES)
    assert read.column("policy_cpu_time_s").null_count == 1 and read.column("starved").null_count == 1


def test_a_served_policy_records_no_cpu_time():
    class Remote(ChunkPolicy):
        def take_served(self):  # the capability a served policy declares (policies/base.py)
            return ServedTotals(nfe=0, server_time_s=0.0)

    policy = Remote(chunk=2, delay=0.02)
    out = run_one(CountdownEnv(succeed_at=6), policy, context(), spec(0))
    assert out.policy_time_s >= 0.06 and out.policy_cpu_time_s is None
    assert is_starved(out.policy_time_s, out.policy_cpu_time_s) is None


def test_the_schema_states_the_rule_the_code_applies():
    (column,) = [c for c in schema.COLUMNS if c.name == "starved"]
    assert f"{STARVED_FACTOR} x policy_cpu_time_s" in column.meaning
    assert f"under {MIN_JUDGED_POLICY_TIME_S} s" in column.meaning
    assert {"policy_cpu_time_s", "starved"} <= schema.TIMING_COLUMNS
