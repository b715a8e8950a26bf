"""A run folder cannot lose or mix rows: one writer at a time, cut-off lines repaired
before the next append, checkpoints identified by content, a full disk reported in one
line (exit 3), and housekeeping that deletes only what the harness wrote."""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import io
import json
import os
import signal
import socket
import subprocess
import sys
import threading
from pathlib import Path

import pyarrow.parquet as pq
import pytest

import results.store
from harness.errors import HarnessError, UsageError
from harness.run.folder import OpenMode
from harness.run.runner import run
from results.lock import RunLock
from results.store import RunDir
from tests.fakes import ChunkPolicy, fake_resolved

pytestmark = pytest.mark.metaworld  # these tests run Meta-World episodes

REPO = Path(__file__).resolve().parent.parent
MT1 = ["run", "--suite", "metaworld/mt1/reach-v3", "--policy", "random", "--quiet"]


def _events(out: Path) -> list[dict]:
    return [json.loads(line) for line in (out / "events.jsonl").read_text().splitlines()]


def _manifest(out: Path) -> dict:
    return json.loads((out / "manifest.json").read_text())


def test_a_second_writer_is_refused_while_the_first_runs_and_the_first_keeps_its_rows(tmp_path):
    out = tmp_path / "run"
    started, go = threading.Event(), threading.Event()

    class Holding(ChunkPolicy):
        def reset(self, episodes):
            if episodes[0].episode_index == 1:  # one row on disk, the run still going
                started.set()
                assert go.wait(30)
            super().reset(episodes)

    first: dict = {}
    thread = threading.Thread(target=lambda: first.update(report=run(fake_resolved(Holding(2), 4), out)))
    thread.start()
    try:
        assert started.wait(30)
        before = sorted(p.name for p in out.iterdir())
        for mode in (OpenMode.RESUME, OpenMode.OVERWRITE, OpenMode.NEW):
            with pytest.raises(UsageError, match="being written by another process") as refused:
                run(fake_resolved(ChunkPolicy(2), 4), out, mode)
            message = str(refused.value)
            assert f"pid {os.getpid()}" in message and socket.gethostname() in message
            assert "started 20" in message
        assert sorted(p.name for p in out.iterdir()) == before  # nothing written
    finally:
        go.set()
        thread.join(30)
    assert first["report"].executed == 4
    assert RunDir(out).read_episodes()["episode_index"].tolist() == [0, 1, 2, 3]
    assert _manifest(out)["status"] == "finished"
    assert not (out / "writer.lock").exists()  # released


def test_a_second_process_is_refused_with_exit_2_then_a_killed_holders_lock_is_taken_over(cli, tmp_path):
    out = tmp_path / "run"
    assert cli(*MT1, "--episodes-per-task", "1", "--out", str(out))[0] == 0
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys, time; from results.lock import RunLock; "
            "RunLock(sys.argv[1]).acquire(); print('held', flush=True); time.sleep(120)",
            str(out),
        ],
        cwd=REPO,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "held"
        manifest = (out / "manifest.json").read_bytes()
        for extra in (["--resume"], ["--overwrite"]):
            code, _, err = cli(*MT1, "--episodes-per-task", "2", "--out", str(out), *extra)
            assert code == 2, err
            assert f"pid {holder.pid} on host {socket.gethostname()}" in err, err
        assert (out / "manifest.json").read_bytes() == manifest
        assert len(RunDir(out).read_episodes()) == 1
    finally:
        os.kill(holder.pid, signal.SIGKILL)
        holder.wait()
    # its flock died with it; the record it left is stale: said in one line, taken over
    assert json.loads((out / "writer.lock").read_text())["pid"] == holder.pid
    code, _, err = cli(*MT1, "--episodes-per-task", "1", "--out", str(out), "--resume")
    assert code == 0, err
    assert f"taking over a stale writer lock (pid {holder.pid} " in err
    assert any(e["event"] == "stale_lock_taken_over" for e in _events(out))
    assert not (out / "writer.lock").exists()


def _killed_mid_write(out: Path, episodes: int, keep: int) -> None:
    """A run of `episodes` rows whose process died after `keep` rows and half of the next."""
    run(fake_resolved(ChunkPolicy(2), episodes), out)
    table = pq.read_table(out / "episodes.parquet").to_pylist()
    (out / "episodes.parquet").unlink()
    lines = [json.dumps(r, default=str) for r in table]
    (out / "pending.jsonl").write_text("".join(line + "\n" for line in lines[:keep]) + lines[keep][:57])
    manifest = _manifest(out)
    (out / "manifest.json").write_text(json.dumps(manifest | {"status": "running"}))


def test_a_cut_off_pending_tail_is_dropped_before_resume_appends_and_nothing_else_is_lost(tmp_path):
    out = tmp_path / "run"
    _killed_mid_write(out, episodes=4, keep=2)
    recorded = RunDir(out).read_episodes()
    assert recorded["episode_index"].tolist() == [0, 1]  # the cut line is not a row

    report = run(fake_resolved(ChunkPolicy(2), 4), out, OpenMode.RESUME)
    assert report.executed == 2 and report.skipped == 2
    assert not (out / "pending.jsonl").exists()  # compaction went through
    df = RunDir(out).read_episodes()
    assert df["episode_index"].tolist() == [0, 1, 2, 3]
    assert df.set_index("episode_index").loc[[0, 1], "started_at"].tolist() == recorded["started_at"].tolist()
    dropped = [e for e in _events(out) if e["event"] == "partial_line_dropped"]
    assert len(dropped) == 1 and dropped[0]["file"] == "pending.jsonl" and dropped[0]["bytes"] == 57


def test_a_cut_off_traces_tail_is_dropped_and_a_line_missing_only_its_newline_is_kept(tmp_path):
    run_dir = RunDir(tmp_path)
    (tmp_path / "traces.jsonl").write_text('{"chunk": 0}\n{"chunk": 1, "comm')
    run_dir.append_traces([{"chunk": 2}, {"chunk": 3}])
    assert [r["chunk"] for r in results.store._read_jsonl(tmp_path / "traces.jsonl")] == [0, 2, 3]

    (tmp_path / "pending.jsonl").write_text('{"a": 1}\n{"a": 2}')  # whole row, newline lost
    assert results.store.repair_tail(tmp_path / "pending.jsonl") == ("completed", b'{"a": 2}')
    assert (tmp_path / "pending.jsonl").read_text() == '{"a": 1}\n{"a": 2}\n'


def _with_checkpoint(resolved, path: Path, digest: str):
    p = resolved.policies[0]
    params = json.dumps({"checkpoint": str(path)})
    resolved.policies[0] = dataclasses.replace(
        p, params_json=params, checkpoint=str(path), checkpoint_sha256=digest, config_id=digest[:12]
    )
    return resolved


def test_resume_refuses_another_checkpoint_at_the_same_path(tmp_path):
    out, ckpt = tmp_path / "run", tmp_path / "model.safetensors"
    old, new = "a" * 12 + "0" * 52, "b" * 12 + "1" * 52
    run(_with_checkpoint(fake_resolved(ChunkPolicy(2), 2), ckpt, old), out)
    before = (out / "episodes.parquet").read_bytes()
    with pytest.raises(UsageError) as refused:
        run(_with_checkpoint(fake_resolved(ChunkPolicy(2), 3), ckpt, new), out, OpenMode.RESUME)
    message = str(refused.value)
    assert "a" * 12 in message and "b" * 12 in message and str(ckpt) in message
    assert (out / "episodes.parquet").read_bytes() == before
    # the same content resumes as before
    assert (
        run(_with_checkpoint(fake_resolved(ChunkPolicy(2), 3), ckpt, old), out, OpenMode.RESUME).executed == 1
    )


def _full_disk_after(monkeypatch, appends: int) -> None:
    """RunDir.append_episode writes `appends` rows, then half a row and fails as a full disk does."""
    real = RunDir.append_episode
    calls = {"n": 0}

    def append(self, row):
        calls["n"] += 1
        if calls["n"] > appends:
            with open(self.path / "pending.jsonl", "a") as fh:
                fh.write('{"run_id": "half')
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        real(self, row)

    monkeypatch.setattr(RunDir, "append_episode", append)


def test_a_full_disk_while_appending_fails_the_run_in_one_line_and_keeps_earlier_rows(tmp_path, monkeypatch):
    out = tmp_path / "run"
    _full_disk_after(monkeypatch, appends=2)
    with pytest.raises(HarnessError) as failed:
        run(fake_resolved(ChunkPolicy(2), 4), out)
    message = str(failed.value)
    assert "\n" not in message and str(out) in message and "disk is full" in message and "MB free" in message
    assert _manifest(out)["status"] == "failed"
    assert RunDir(out).read_episodes()["episode_index"].tolist() == [0, 1]
    assert any(e["event"] == "run_failed" for e in _events(out))


def test_a_full_disk_while_compacting_keeps_pending_rows_and_no_temporary(tmp_path, monkeypatch):
    out = tmp_path / "run"

    def write_table(table, where):
        Path(where).write_bytes(b"PAR1 half a table")
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(results.store.pq, "write_table", write_table)
    with pytest.raises(HarnessError, match=r"disk is full.*compacting"):
        run(fake_resolved(ChunkPolicy(2), 3), out)
    assert _manifest(out)["status"] == "failed"
    assert [p.name for p in out.iterdir() if p.name.endswith(".tmp")] == []
    assert not (out / "episodes.parquet").exists() and len(RunDir(out).pending_rows()) == 3
    monkeypatch.undo()
    assert run(fake_resolved(ChunkPolicy(2), 3), out, OpenMode.RESUME).skipped == 3
    assert pq.read_table(out / "episodes.parquet").num_rows == 3


def test_a_full_disk_exits_3_with_one_line(cli, tmp_path, monkeypatch):
    out = tmp_path / "run"
    _full_disk_after(monkeypatch, appends=1)
    code, _, err = cli(*MT1, "--episodes-per-task", "2", "--out", str(out))
    assert code == 3
    assert len(err.strip().splitlines()) == 1 and "disk is full" in err and str(out) in err
    assert _manifest(out)["status"] == "failed" and len(RunDir(out).read_episodes()) == 1


def test_temporaries_left_by_a_kill_are_removed_by_the_next_writer(tmp_path):
    out = tmp_path / "run"
    run(fake_resolved(ChunkPolicy(2), 2), out)
    left = [out / ".episodes.parquet.4242.tmp", out / ".manifest.json.4242.tmp"]
    for p in left:
        p.write_bytes(b"half")
    assert run(fake_resolved(ChunkPolicy(2), 2), out, OpenMode.RESUME).skipped == 2
    assert not any(p.exists() for p in left)
    removed = [e for e in _events(out) if e["event"] == "temporaries_removed"]
    assert removed and sorted(removed[0]["files"]) == sorted(p.name for p in left)


def _left_by_a_kill(out: Path) -> list[Path]:
    """A finished run plus the temporaries a writer killed mid-compaction leaves."""
    run(fake_resolved(ChunkPolicy(2), 2), out)
    left = [out / ".episodes.parquet.4242.tmp", out / ".manifest.json.4242.tmp"]
    for p in left:
        p.write_bytes(b"half")
    return left


@pytest.mark.parametrize(
    "command",
    [["show", "{out}"], ["leaderboard", "{out}"], ["gate", "--baseline", "{out}", "--candidate", "{out}"]],
)
def test_temporaries_left_by_a_kill_are_removed_by_a_command_that_only_reads(cli, tmp_path, command):
    out = tmp_path / "run"
    left = _left_by_a_kill(out)
    code, _, err = cli(*(part.format(out=out) for part in command))
    assert code == 0, err
    assert not any(p.exists() for p in left)
    removed = [e for e in _events(out) if e["event"] == "temporaries_removed"]
    assert sorted(removed[0]["files"]) == sorted(p.name for p in left)
    assert not (out / "writer.lock").exists()  # the lock taken to tidy up is gone again


def test_a_live_writers_temporaries_are_kept_by_a_reader(cli, tmp_path):
    out = tmp_path / "run"
    left = _left_by_a_kill(out)
    lock = RunLock(out)
    lock.acquire()  # as a writer holds it while compacting (flock: per open file)
    try:
        assert cli("show", str(out))[0] == 0
        assert all(p.read_bytes() == b"half" for p in left)
        assert json.loads((out / "writer.lock").read_text())["pid"] == os.getpid()
    finally:
        lock.release()
    assert not any(e["event"] == "temporaries_removed" for e in _events(out))


def test_a_reader_tidying_up_leaves_a_killed_writers_stale_lock_for_the_next_writer(cli, tmp_path):
    out = tmp_path / "run"
    left = _left_by_a_kill(out)
    dead = subprocess.Popen([sys.executable, "-c", ""])
    dead.wait()
    stale = {"pid": dead.pid, "host": socket.gethostname(), "started_at": "2026-01-01T00:00:00+00:00"}
    (out / "writer.lock").write_text(json.dumps(stale) + "\n")
    assert cli("show", str(out))[0] == 0
    assert not any(p.exists() for p in left)
    assert json.loads((out / "writer.lock").read_text()) == stale
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        run(fake_resolved(ChunkPolicy(2), 2), out, OpenMode.RESUME)
    assert f"taking over a stale writer lock (pid {dead.pid} " in err.getvalue()
    assert any(e["event"] == "stale_lock_taken_over" for e in _events(out))


def test_overwrite_deletes_only_what_the_harness_wrote_and_refuses_other_files(tmp_path):
    out = tmp_path / "run"
    run(fake_resolved(ChunkPolicy(2), 3), out)
    (out / "notes.txt").write_text("mine")
    (out / "plots").mkdir()
    before = sorted(p.name for p in out.iterdir())
    with pytest.raises(UsageError, match=r"did not write \(notes\.txt, plots/\); refusing to delete it"):
        run(fake_resolved(ChunkPolicy(2), 1), out, OpenMode.OVERWRITE)
    assert sorted(p.name for p in out.iterdir()) == before

    (out / "notes.txt").unlink()
    (out / "plots").rmdir()
    (out / ".episodes.parquet.4242.tmp").write_bytes(b"half")
    old_id = _manifest(out)["run_id"]
    run(fake_resolved(ChunkPolicy(2), 1), out, OpenMode.OVERWRITE)
    assert _manifest(out)["run_id"] != old_id and len(RunDir(out).read_episodes()) == 1
    assert sorted(p.name for p in out.iterdir()) == ["episodes.parquet", "events.jsonl", "manifest.json"]


def test_overwrite_through_a_symlink_is_refused(tmp_path):
    out, link = tmp_path / "run", tmp_path / "link"
    run(fake_resolved(ChunkPolicy(2), 2), out)
    link.symlink_to(out)
    with pytest.raises(UsageError, match="symbolic link"):
        run(fake_resolved(ChunkPolicy(2), 1), link, OpenMode.OVERWRITE)
    assert len(RunDir(out).read_episodes()) == 2 and link.is_symlink()
