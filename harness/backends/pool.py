"""`--workers N` on the local backend: N worker processes on this machine.

Workers are started with multiprocessing's `spawn` context: a fresh interpreter, since
torch's thread pools and MuJoCo's GL state do not survive a fork of a process that has
started them. Each worker rebuilds the run's policies and suite from the config (a
built policy is not sent between processes), sets its own torch/BLAS threads, and then
runs the episodes it is sent with the same episode loop as the in-process backend
(harness/backends/local.py `Worker`), sending each event (an episode started, ended) as
it happens.

Each worker talks to the parent over its own pipe, not a shared queue: a worker killed
mid-write (SIGKILL, a segfault) can then leave at most a cut message on its own pipe,
which reads as end-of-file, never a lock held forever that would stall the others.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import signal
from multiprocessing import connection, get_context
from pathlib import Path
from typing import Any

from harness.backends.local import WorkerSpec, start_worker
from harness.backends.scheduler import Event, JobId

_PR_SET_PDEATHSIG = 1


def lost_reason(exitcode: int | None) -> str:
    """Why a worker process is gone, in words (the failure row's reason if it stays gone)."""
    if exitcode is None:
        return "stopped answering"
    if exitcode < 0:
        try:
            name = signal.Signals(-exitcode).name
        except ValueError:
            name = f"signal {-exitcode}"
        if name == "SIGKILL":
            return "killed by SIGKILL (the out-of-memory killer, or a kill)"
        if name == "SIGSEGV":
            return "crashed with SIGSEGV (a segmentation fault)"
        return f"killed by {name}"
    return f"exited with status {exitcode}"


def die_with_parent(parent: int | None = None) -> None:
    """Linux: the kernel sends SIGKILL to this worker if the parent dies (a SIGKILLed
    parent cannot stop its workers itself; --resume re-runs what they held). `parent`:
    the parent's pid, to catch a parent that died before this call took effect."""
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)
    if parent is not None and os.getppid() != parent:
        os._exit(1)


def _children(pid: int) -> list[int]:
    """`pid`'s child processes, from /proc (Linux; none elsewhere or once it is gone)."""
    found: list[int] = []
    with contextlib.suppress(OSError):
        for task in Path(f"/proc/{pid}/task").iterdir():
            with contextlib.suppress(OSError, ValueError):
                found += [int(c) for c in (task / "children").read_text().split()]
    return found


def kill_tree(pid: int) -> None:
    """SIGKILL a worker and every process under it. A worker may have children of its own
    (glfw's library probe runs a Python child while mujoco imports); killed alone, it
    leaves them to write into a pipe nobody reads, and their BrokenPipeError tracebacks
    land on the user's terminal after the run has said it stopped. Each process is
    stopped (SIGSTOP) before its children are listed, so none can start another unseen."""
    stopped: list[int] = []
    pending = [pid]
    while pending:
        current = pending.pop()
        with contextlib.suppress(OSError):
            os.kill(current, signal.SIGSTOP)
            stopped.append(current)
            pending += _children(current)
    for target in reversed(stopped):  # the deepest first, the worker last
        with contextlib.suppress(OSError):
            os.kill(target, signal.SIGKILL)


def worker_main(conn: Any, worker_id: str, spec: WorkerSpec) -> None:
    """A worker's life: start (harness/backends/local.py `start_worker`), warm up, say
    ready, run groups of episodes until told to stop, sending each event as it happens (a
    finished episode's row is written by the parent while the rest of its batch runs)."""
    die_with_parent()
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C stops the parent, which stops us
    try:
        worker, record = start_worker(spec, worker_id)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            conn.send(("error", f"{type(exc).__name__}: {exc}"))
        return
    try:
        for event in worker.warming():  # each policy's first calls, held to --episode-timeout
            conn.send(event)
        conn.send(("ready", record | {"warm_up": worker.warm_up}))
        while True:
            message = conn.recv()
            if message is None:
                break
            group, alone = message
            for event in worker.run(group, alone):
                conn.send(event)
    except (EOFError, OSError):
        pass  # the parent is gone or done: a worker still starting when the work ran out
    finally:
        worker.close()


class ProcessWorkers:
    """The `Workers` of harness/backends/scheduler.py as spawned processes."""

    def __init__(self, spec: WorkerSpec):
        self.context = get_context("spawn")
        self.spec = spec
        self.procs: dict[int, Any] = {}
        self.conns: dict[int, Any] = {}
        self.started = 0

    def start(self, slot: int) -> str:
        worker_id = f"local-{self.started}"
        self.started += 1
        mine, theirs = self.context.Pipe()
        args = (theirs, worker_id, self.spec)
        proc = self.context.Process(target=worker_main, args=args, name=f"dvla-{worker_id}", daemon=True)
        proc.start()
        theirs.close()
        self.procs[slot], self.conns[slot] = proc, mine
        return worker_id

    def submit(self, slot: int, group: list[JobId], alone: bool) -> None:
        try:
            self.conns[slot].send((group, alone))
        except OSError:
            pass  # the worker is gone: its sentinel says so at the next wait

    def _drain(self, slot: int, events: list[Event]) -> bool:
        """Read what the slot's worker sent; False when its pipe is closed or cut."""
        conn = self.conns[slot]
        try:
            while conn.poll():
                kind, payload = conn.recv()
                events.append(Event(slot, kind, payload))
        except (EOFError, OSError):
            return False
        return True

    def _forget(self, slot: int) -> Any:
        proc = self.procs.pop(slot)
        self.conns.pop(slot).close()
        return proc

    def wait(self, timeout: float) -> list[Event]:
        waiting = {conn: slot for slot, conn in self.conns.items()}
        waiting |= {proc.sentinel: slot for slot, proc in self.procs.items()}
        events: list[Event] = []
        lost = set()
        for ready in connection.wait(list(waiting), timeout):
            slot = waiting[ready]
            if slot in lost or slot not in self.procs:
                continue
            alive = self._drain(slot, events)
            if not alive or not self.procs[slot].is_alive():
                proc = self._forget(slot)
                proc.join(5)
                lost.add(slot)
                events.append(Event(slot, "lost", lost_reason(proc.exitcode)))
        return events

    def kill(self, slot: int) -> None:
        if slot in self.procs:
            proc = self._forget(slot)
            if proc.pid is not None:
                kill_tree(proc.pid)
            proc.join(5)

    def shutdown(self) -> None:
        for conn in self.conns.values():
            with contextlib.suppress(OSError):
                conn.send(None)
        for slot in list(self.procs):
            proc = self._forget(slot)
            proc.join(2)
            if proc.is_alive() and proc.pid is not None:
                kill_tree(proc.pid)
                proc.join(5)
