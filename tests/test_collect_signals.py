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
        proc = subprocess.Popen(  # SIGINT as a terminal leaves it, however pytest was started
            command, cwd=REPO, stdout=subprocess.DEVNULL, stderr=stderr, start_new_session=True,
            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
        )  # fmt: skip
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


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def test_a_stopped_worker_takes_its_own_children_with_it():
    """A worker killed alone left its children (glfw's library probe, a Python child that
    mujoco's import starts) to print BrokenPipeError tracebacks after collect had said it
    stopped; a child that ignores SIGINT, as the workers' children do, goes too."""
    from harness.backends.pool import kill_tree

    script = (
        "import signal, subprocess, sys, time\n"
        "signal.signal(signal.SIGINT, signal.SIG_IGN)\n"
        'below = \'import subprocess, time; print(subprocess.Popen(["sleep", "60"]).pid, flush=True); time.sleep(60)\'\n'
        "child = subprocess.Popen([sys.executable, '-c', below])\n"
        "print(child.pid, flush=True)\n"
        "time.sleep(60)\n"
    )
    worker = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    try:  # the child's pid, and its own child's (a grandchild of the worker), in either order
        below = [int(worker.stdout.readline()) for _ in range(2)]
        assert len(below) == 2 and all(_alive(pid) for pid in below)
        kill_tree(worker.pid)
        assert worker.wait(timeout=10) == -signal.SIGKILL
        assert _until(lambda: not any(_alive(pid) for pid in below), 10), [_alive(p) for p in below]
    finally:
        worker.kill()


def test_killing_a_tree_whose_worker_is_gone_is_quiet():
    from harness.backends.pool import kill_tree

    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    kill_tree(gone.pid)  # reaped already: nothing to kill, no error


def test_a_ctrl_c_while_the_workers_start_is_held_not_lost():
    """The parent blocks SIGINT while it spawns the workers (so none is interrupted while it
    imports); a Ctrl-C in that window is raised when it closes, not lost (it was once, and
    the collection ran to its end)."""
    from harness.collect_pool import _sigint_held

    before = signal.signal(signal.SIGINT, signal.default_int_handler)  # as a terminal starts Python
    try:
        with pytest.raises(KeyboardInterrupt):
            with _sigint_held():
                os.kill(os.getpid(), signal.SIGINT)
                time.sleep(0.05)  # held: no KeyboardInterrupt inside the window
                inside = True
        assert inside
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
        assert signal.SIGINT not in signal.pthread_sigmask(signal.SIG_BLOCK, set())
    finally:
        signal.signal(signal.SIGINT, before)


def test_a_process_that_ignores_ctrl_c_keeps_ignoring_it_while_the_workers_start():
    """A collection started as a shell script's background job has SIGINT ignored from the
    start: a SIGINT in the window is dropped, as outside it, and the handler stays ignored."""
    from harness.collect_pool import _sigint_held

    before = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        try:
            with _sigint_held():
                os.kill(os.getpid(), signal.SIGINT)
                time.sleep(0.05)
        except KeyboardInterrupt:
            pytest.fail("a SIGINT the process ignores was raised as KeyboardInterrupt")
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
        assert signal.SIGINT not in signal.pthread_sigmask(signal.SIG_BLOCK, set())
    finally:
        signal.signal(signal.SIGINT, before)
