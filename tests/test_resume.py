"""A run killed with SIGKILL loses at most the episode in flight and resumes exactly."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pyarrow.parquet as pq

from results.store import RunDir

REPO = Path(__file__).resolve().parent.parent
ARGS = [
    "run",
    "--suite",
    "metaworld/mt1/reach-v3",
    "--policy",
    "random",
    "--episodes-per-task",
    "10",
    "--quiet",
]


def _wait_for_rows(out, n: int) -> None:
    """Until the running process has recorded n episodes (or two minutes pass)."""
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        pending = out / "pending.jsonl"
        if pending.is_file() and pending.read_text().count("\n") >= n:
            return
        time.sleep(0.02)


def test_sigkill_then_resume_records_each_episode_once(tmp_path):
    out = tmp_path / "run"
    proc = subprocess.Popen(
        [sys.executable, "-m", "harness", *ARGS, "--out", str(out)],
        cwd=REPO,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    _wait_for_rows(out, 3)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    before = RunDir(out).read_episodes()  # every complete row parses; a cut line is dropped
    assert 3 <= len(before) < 10, "the run must be killed mid-way"
    assert not (out / "episodes.parquet").exists()

    done = subprocess.run(
        [sys.executable, "-m", "harness", *ARGS, "--out", str(out), "--resume"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    # the killed process's lock died with it; its record is reported stale and taken over
    assert f"taking over a stale writer lock (pid {proc.pid} " in done.stderr
    assert not (out / "writer.lock").exists()
    df = RunDir(out).read_episodes()
    assert sorted(df["episode_index"]) == list(range(10))
    raw = pq.read_table(out / "episodes.parquet").to_pandas()
    assert len(raw) == 10 and raw["episode_index"].is_unique
    assert set(df["run_id"]) == set(before["run_id"])  # the same run, continued
    kept = df.set_index("episode_index").loc[before["episode_index"], "started_at"]
    assert list(kept) == list(before["started_at"])  # recorded episodes were not re-run


def test_resume_refuses_a_folder_of_another_config(cli, tmp_path):
    out = tmp_path / "run"
    base = ["run", "--suite", "metaworld/mt1/reach-v3", "--episodes-per-task", "1", "--out", str(out)]
    assert cli(*base, "--policy", "random", "--quiet")[0] == 0
    before = sorted(p.name for p in out.rglob("*"))
    code, _, err = cli(*base, "--policy", "random:seed=1", "--resume")
    assert code == 2 and "belongs to a different config" in err and "seed" in err
    code, _, err = cli(*base, "--policy", "random")
    assert code == 2 and "--resume" in err and "--overwrite" in err
    assert sorted(p.name for p in out.rglob("*")) == before


def test_sigterm_stops_cleanly_and_compacts(tmp_path):
    out = tmp_path / "run"
    proc = subprocess.Popen(
        [sys.executable, "-m", "harness", *ARGS, "--out", str(out)],
        cwd=REPO,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    _wait_for_rows(out, 2)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130
    assert "--resume" in err
    assert not (out / "pending.jsonl").exists()
    rows = pq.read_table(out / "episodes.parquet").num_rows
    assert 2 <= rows < 10
