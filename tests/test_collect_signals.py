"""`collect --workers 2` stopped as CI stops a job (SIGTERM), as a terminal does (Ctrl-C:
SIGINT to the whole process group) or killed outright (SIGKILL): no process of the
collection is left behind, and a stop it can handle is one line and exit 130."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.metaworld  # the workers collect Meta-World episodes

REPO = Path(__file__).resolve().parent.parent


def _session(leader: int) -> dict[int, str]:
    """The live processes of the session `leader` started (its workers, multiprocessing's
    resource tracker; the leader aside), pid -> command line, from /proc."""
    found = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) == leader:
            continue
        try:
            fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            command = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue  # gone meanwhile
        if int(fields[3]) == leader and fields[0] != "Z":  # its session, not a zombie
            found[int(entry.name)] = command
    return found


def _until(condition, seconds: float) -> bool:
    deadline = time.monotonic() + seconds
    while not condition():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.1)
    return True


@pytest.mark.parametrize("stop", ["SIGTERM", "SIGINT to the group", "SIGKILL"])
def test_no_process_of_the_collection_outlives_its_parent(tmp_path, stop):
    out, err = tmp_path / "demos", tmp_path / "stderr.txt"
    command = [
        sys.executable, "-m", "harness", "collect", "--suite", "metaworld/mt1/reach-v3", "--policy",
        "scripted", "--episodes-per-task", "400", "--workers", "2", "--out", str(out), "--quiet",
    ]  # fmt: skip
    with err.open("w") as stderr:  # a file, not a pipe nobody reads
        proc = subprocess.Popen(
            command, cwd=REPO, stdout=subprocess.DEVNULL, stderr=stderr, start_new_session=True
        )
    try:
        # both workers and the resource tracker are up; then they build and collect a while
        assert _until(lambda: len(_session(proc.pid)) >= 3, 120), _session(proc.pid)
        time.sleep(1.0)
        if stop == "SIGINT to the group":
            os.killpg(proc.pid, signal.SIGINT)
        else:
            os.kill(proc.pid, getattr(signal, stop))
        code = proc.wait(timeout=60)
        assert _until(lambda: not _session(proc.pid), 20), _session(proc.pid)
    finally:
        proc.kill()
        for pid in _session(proc.pid):  # whatever a failure left, not left running
            os.kill(pid, signal.SIGKILL)
    said = err.read_text()
    if stop == "SIGKILL":
        assert code == -signal.SIGKILL
    else:
        assert code == 130 and "Traceback" not in said, said
        assert said.strip().splitlines() == [
            f"interrupted; nothing was written to {out} (collect writes its folder once, at the end): "
            "run the same command again"
        ]
    assert not out.exists() and not out.with_name(out.name + ".tmp").exists()
