"""A failing policy, checkpoint or policy server ends a run cleanly, never by hanging it
or by recording misleading rows: first calls held to --episode-timeout, strict JSON in
every written file, a checkpoint swapped under running workers, a policy server that
restarts."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pytest

from harness.backends import Execution
from harness.errors import HarnessError
from harness.runner import run
from policies.base import ChunkBatch
from results.store import RunDir
from tests.fakes import ChunkPolicy, FakeBuild, fake_resolved

MT1 = ["run", "--suite", "metaworld/mt1/reach-v3", "--policy", "random", "--episodes-per-task", "1"]


def _within(seconds: float, call):
    """call() in a thread, failing the test (not hanging it) if it has not returned in time."""
    outcome: dict = {}

    def target():
        try:
            outcome["value"] = call()
        except BaseException as exc:
            outcome["error"] = exc

    thread = threading.Thread(target=target, daemon=True)
    thread.start()
    thread.join(seconds)
    assert not thread.is_alive(), f"still running after {seconds} s: the run hangs"
    if "error" in outcome:
        raise outcome["error"]
    return outcome["value"]


@pytest.mark.parametrize("workers", [1, 2])
def test_a_policy_that_hangs_on_every_call_ends_the_run_with_timeout_rows(tmp_path, workers):
    # every episode hangs in its first call (reset), so the warm-up on episode 0 does too
    build = FakeBuild(faults=((0, "hang"), (1, "hang")), episodes=2)
    execution = Execution(workers=workers, episode_timeout=1.0, rebuild=build)
    report = _within(90, lambda: run(build(), tmp_path / "r", execution=execution))
    rows = report.run_dir.read_episodes()
    assert sorted(rows["episode_index"]) == [0, 1]
    assert rows["failure_reason"].str.startswith("timeout:").all()
    assert "warm-up" in " ".join(rows["failure_reason"])
    assert report.run_dir.read_manifest()["status"] == "finished"


class CheckHangs(ChunkPolicy):
    def check_spaces(self, observation_space, action_space) -> None:
        time.sleep(3600)


def test_a_check_spaces_that_never_returns_stops_the_run_naming_the_policy(tmp_path):
    start = time.monotonic()
    with pytest.raises(HarnessError) as stopped:
        _within(30, lambda: run(fake_resolved(CheckHangs()), tmp_path / "r", execution=Execution(episode_timeout=1.0)))
    assert time.monotonic() - start < 15
    assert "policy fake" in str(stopped.value) and "check_spaces" in str(stopped.value)
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize("value", ["inf", "nan", "-1"])
def test_a_timeout_that_is_not_a_finite_positive_number_is_refused(cli, tmp_path, monkeypatch, value):
    monkeypatch.chdir(tmp_path)
    code, _out, err = cli(*MT1, "--episode-timeout", value, "--out", str(tmp_path / "out"))
    assert code == 2 and "--episode-timeout must be a positive, finite number of seconds" in err
    assert list(tmp_path.iterdir()) == []


class NonFiniteTrace(ChunkPolicy):
    """A decode trace holding a NaN and a numpy infinity (a confidence of an empty set)."""

    def act(self, observations: Sequence[object]) -> ChunkBatch:
        batch = super().act(observations)
        batch.trace = [{"confidence": float("nan"), "margin": np.float32("inf"), "order": [0, 1]}]
        return batch


def _refuse(constant: str):
    raise ValueError(f"not strict JSON: {constant}")


def test_every_json_file_a_run_writes_parses_strictly(tmp_path):
    out = tmp_path / "r"
    report = run(fake_resolved(NonFiniteTrace(2), episodes=3, fail_episode=1), out, traces=True)
    assert report.failed == 1
    run_dir = RunDir(out)
    # what the harness records beside rows can be non-finite too (a rate over zero seconds)
    run_dir.log_event("probe", rate=float("inf"), ratio=np.float64("nan"))
    run_dir.write_manifest(run_dir.read_manifest() | {"probe": {"rate": float("-inf")}})
    files = sorted(p for p in out.rglob("*") if p.suffix in (".json", ".jsonl"))
    assert {p.name for p in files} >= {"manifest.json", "events.jsonl", "traces.jsonl"}
    for path in files:
        text = path.read_text()
        lines = text.splitlines() if path.suffix == ".jsonl" else [text]
        for line in lines:
            json.loads(line, parse_constant=_refuse)
    trace = json.loads((out / "traces.jsonl").read_text().splitlines()[0])
    assert trace["confidence"] is None and trace["margin"] is None and trace["order"] == [0, 1]
    assert run_dir.read_manifest()["probe"] == {"rate": None}


def test_a_checkpoint_swapped_under_running_workers_stops_the_run_naming_both_hashes(
    cli, tmp_path, monkeypatch
):
    from harness.backends.pool import ProcessWorkers
    from harness.config import sha256_file
    from policies.dvla.checkpoint import load, save
    from tests.test_dvla_policies import make_checkpoint

    ckpt, other = tmp_path / "m.safetensors", tmp_path / "other.safetensors"
    make_checkpoint(ckpt, "bidirectional")
    changed = load(ckpt)
    changed.meta["recipe"] = "retrained"
    save(changed, other)
    hashed, swapped = sha256_file(str(ckpt)), sha256_file(str(other))
    start = ProcessWorkers.start

    def swap_then_start(self, slot):  # the file is replaced after the run hashed it
        if other.exists():
            other.replace(ckpt)
        return start(self, slot)

    monkeypatch.setattr(ProcessWorkers, "start", swap_then_start)
    out = tmp_path / "run"
    argv = ["run", "--suite", "metaworld/mt1/reach-v3", "--episodes-per-task", "2", "--quiet"]
    argv += ["--policy", f"bidirectional:checkpoint={ckpt}", "--workers", "2", "--out", str(out)]
    code, _out, err = cli(*argv)
    assert code == 3, err
    assert str(ckpt) in err and hashed in err and swapped in err
    run_dir = RunDir(out)
    assert len(run_dir.read_episodes()) == 0  # no row claims the hashed model ran
    assert run_dir.read_manifest()["status"] == "failed"
