"""A failing policy, checkpoint or policy server ends a run cleanly, never by hanging it
or by recording misleading rows: first calls held to --episode-timeout, strict JSON in
every written file, a checkpoint swapped under running workers, a policy server that
restarts."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from harness.backends import Execution
from harness.errors import HarnessError
from harness.run.runner import run
from policies.base import ChunkBatch
from results.store import RunDir
from tests.fakes import ChunkPolicy, FakeBuild, fake_resolved

pytestmark = pytest.mark.metaworld  # these tests run Meta-World episodes

SUITE = "metaworld/mt1/reach-v3"
MT1 = ["run", "--suite", SUITE, "--policy", "random", "--episodes-per-task", "1"]
REPO = Path(__file__).resolve().parent.parent


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
        _within(
            30,
            lambda: run(
                fake_resolved(CheckHangs()), tmp_path / "r", execution=Execution(episode_timeout=1.0)
            ),
        )
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


def _serve(port: int = 0) -> tuple[subprocess.Popen, str]:
    """`dvla-harness serve` of the random policy in its own process; (process, ws:// address)."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "harness", "serve", "--policy", "random", "--suite", SUITE, "--port", str(port)],
        cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        env=os.environ | {"OMP_NUM_THREADS": "1", "COLUMNS": "200"},
    )  # fmt: skip
    line = proc.stdout.readline()
    match = re.search(r"on (ws://[0-9.]+:[0-9]+)", line)
    assert match, line
    return proc, match.group(1)


def _remote_run(cli, out: Path, url: str, *extra: str) -> tuple[int, str]:
    code, _, err = cli(
        "run", "--suite", SUITE, "--policy", f"remote:url={url}", "--episodes-per-task", "4",
        "--out", str(out), "--quiet", *extra,
    )  # fmt: skip
    return code, err


def test_a_policy_server_restarted_mid_run_loses_no_episode(cli, tmp_path):
    pytest.importorskip("msgpack")
    pytest.importorskip("websockets")
    out = tmp_path / "run"
    servers = [_serve()]
    url = servers[0][1]

    def restart() -> None:  # once the first row is on disk: kill the server, start it again
        pending = out / "pending.jsonl"
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and not (pending.exists() and pending.read_text().count("\n")):
            time.sleep(0.05)
        servers[0][0].kill()
        servers[0][0].wait()
        time.sleep(1.0)  # and it takes seconds to load again: longer than three quick attempts
        servers.append(_serve(int(url.rsplit(":", 1)[1])))

    restarter = threading.Thread(target=restart, daemon=True)
    restarter.start()
    try:
        code, err = _remote_run(cli, out, url)
        restarter.join(60)
        assert len(servers) == 2, "the server was not restarted during the run"
        rows = RunDir(out).read_episodes().sort_values("episode_index")
        reasons = rows["failure_reason"].dropna().tolist()
        # at most the episode in flight when the server died is lost, as a lost connection
        assert len(rows) == 4 and len(reasons) <= 1, reasons
        assert all(r.startswith("ConnectionLost:") and "closed the connection" in r for r in reasons)
        assert code == (1 if reasons else 0), err
        # a plain --resume runs a lost connection's episode again, and only that
        code, err = _remote_run(cli, out, url, "--resume")
        assert code == 0, err
        again = RunDir(out).read_episodes()
        assert len(again) == 4 and again["failure_reason"].isna().all()
    finally:
        for proc, _ in servers:
            proc.kill()
            proc.wait()


def test_rows_of_a_lost_connection_are_run_again_by_a_plain_resume(cli, tmp_path):
    pytest.importorskip("msgpack")
    from websockets.sync.server import serve

    from policies.wire import pack, unpack

    connections = [0]

    def handle(ws) -> None:  # the first connection drops on its fourth call (mid-episode)
        connections[0] += 1
        ws.send(pack({"server": "openpi-like"}))
        for call, data in enumerate(ws):
            unpack(data)
            if connections[0] == 1 and call == 3:
                ws.close()
                return
            ws.send(pack({"actions": np.zeros((4, 4), np.float32)}))

    server = serve(handle, "127.0.0.1", 0, compression=None)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    url = f"ws://127.0.0.1:{server.socket.getsockname()[1]}"
    out = tmp_path / "run"
    try:
        code, _, _ = cli(
            *MT1[:3],
            "--policy",
            f"remote:url={url}",
            "--episodes-per-task",
            "2",
            "--out",
            str(out),
            "--quiet",
        )
        rows = RunDir(out).read_episodes().sort_values("episode_index")
        lost = rows["failure_reason"].iloc[0]
        assert code == 1 and "closed the connection" in lost and pd.isna(rows["failure_reason"].iloc[1])
        code, _, _ = cli("run", "--out", str(out), "--resume", "--quiet")
        rows = RunDir(out).read_episodes()
        assert code == 0 and rows["failure_reason"].isna().all() and len(rows) == 2
        assert lost.startswith("ConnectionLost:")  # the server's failure, named as such
        events = [json.loads(line)["event"] for line in (out / "events.jsonl").read_text().splitlines()]
        assert events.count("episode_failed") == 1  # the re-run did not fail again
    finally:
        server.shutdown()
