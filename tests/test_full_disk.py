"""A disk that fills up while a run starts (its first manifest written, then no room): every
write the harness makes (the manifest's session records, the event log, rows) stops the run
in one line, exit 3, with the manifest saying `failed` and the run resumable, as a full disk
at compaction does (tests/test_run_folder.py)."""

from __future__ import annotations

import errno
import json
import os
from pathlib import Path

import pytest

import results.store
from harness.backends import Execution
from harness.errors import HarnessError
from harness.run.folder import OpenMode
from harness.run.runner import run
from results.store import RunDir
from tests.fakes import ChunkPolicy, FakeBuild, fake_resolved

pytestmark = pytest.mark.metaworld  # the CLI test runs a Meta-World episode


def full_disk(monkeypatch, room: int) -> None:
    """The disk has room for `room` more writes (manifest writes, log lines, rows); every
    one after fails as a full disk does. Writing a file over its own bytes needs no room
    (RunDir.overwrite_manifest), so it is left alone, as on a real disk."""
    left = {"writes": room}

    def needing_room(real):
        def write(*args, **kwargs):
            if left["writes"] <= 0:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            left["writes"] -= 1
            return real(*args, **kwargs)

        return write

    monkeypatch.setattr(results.store, "atomic_write", needing_room(results.store.atomic_write))
    for name in ("log_event", "append_episode", "append_traces"):
        monkeypatch.setattr(RunDir, name, needing_room(getattr(RunDir, name)))


def _status(out: Path) -> str:
    return json.loads((out / "manifest.json").read_text())["status"]


# In one process the run writes: the manifest (1), the run_started event (2), the
# session's execution record (3), the warm-up record (4), then a row per episode.
@pytest.mark.parametrize(
    ("room", "doing"),
    [(1, "writing events.jsonl (run_started)"), (2, "writing manifest.json"), (3, "writing manifest.json")],
)
def test_a_disk_full_at_the_start_fails_in_one_line_says_failed_and_resumes(
    tmp_path, monkeypatch, room, doing
):
    out = tmp_path / "run"
    full_disk(monkeypatch, room)
    with pytest.raises(HarnessError) as failed:
        run(fake_resolved(ChunkPolicy(2), 3), out)
    message = str(failed.value)
    assert "\n" not in message and "the disk is full" in message and doing in message and str(out) in message
    assert _status(out) == "failed"
    monkeypatch.undo()
    report = run(fake_resolved(ChunkPolicy(2), 3), out, OpenMode.RESUME)
    assert report.executed == 3 and _status(out) == "finished"


def test_a_disk_full_when_a_worker_reports_ready_fails_the_same_way(tmp_path, monkeypatch):
    out = tmp_path / "run"
    full_disk(monkeypatch, 3)  # the manifest, run_started, the execution record; no room for a worker's
    build = FakeBuild(episodes=2)
    with pytest.raises(HarnessError, match=r"the disk is full .* while writing manifest\.json"):
        run(build(), out, execution=Execution(workers=2, rebuild=build))
    assert _status(out) == "failed"
    monkeypatch.undo()
    assert run(build(), out, OpenMode.RESUME).executed == 2


def test_the_cli_exits_3_with_one_line(cli, tmp_path, monkeypatch):
    out = tmp_path / "run"
    full_disk(monkeypatch, 3)  # the warm-up record finds no room
    code, _, err = cli(
        "run", "--suite", "metaworld/mt1/reach-v3", "--policy", "random", "--episodes-per-task", "1",
        "--out", str(out), "--quiet",
    )  # fmt: skip
    assert code == 3 and len(err.strip().splitlines()) == 1, err
    assert "the disk is full" in err and "continue with --resume" in err and "Traceback" not in err
    assert _status(out) == "failed"
