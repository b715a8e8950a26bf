"""`collect --workers N`: ranges of episodes on N spawned processes.

Each worker builds the policy and suite once, from the checkpoint bytes the parent hashed,
and runs the ranges it is sent through collect's own episode code (harness/collect.py).
The workers die with the parent: the kernel kills them when it is killed (SIGKILL, the
out-of-memory killer), and on an error, Ctrl-C or SIGTERM the parent kills them before it
says so, instead of waiting for the ranges they run; a worker ignores Ctrl-C, which the
terminal sends to the whole group. Nothing is written until every range is back.
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
from collections.abc import Callable, Iterator
from typing import Any

from harness.config import CheckpointPin, ResolvedRun, check_checkpoints, checkpoint_pins, resolve
from harness.errors import HarnessError

Job = tuple[int, int, int]  # task's position, first and end position in its episode list

_WORKER_RUN: ResolvedRun | None = None
COLLECT_ADVICE = "nothing was written; put the original back, or collect again for the new file"


def _worker_job(
    run_job: Callable[..., Any],
    job: Job,
    action_noise: float,
    config: Any,
    pins: tuple[CheckpointPin, ...],
    workers: int = 1,
) -> Any:
    """A collection worker (a fresh `spawn` interpreter) builds its policy and suite on its
    first range, from the checkpoint bytes the parent hashed (`check_checkpoints`, as run's
    workers do): a file swapped mid-collection stops it instead of mixing two models' data.
    Built here, not in the pool's initializer, so its errors reach the parent whole."""
    global _WORKER_RUN
    if _WORKER_RUN is None:
        from harness.threads import apply_threads

        apply_threads(None, workers)  # the worker's share of the cores, before torch loads
        check_checkpoints(pins, advice=COLLECT_ADVICE)
        _WORKER_RUN = resolve(config, announce=False)
        check_checkpoints(pins, _WORKER_RUN, advice=COLLECT_ADVICE)
    return run_job(_WORKER_RUN, job, action_noise, None)


def _worker_started(parent: int) -> None:
    """A collection worker's first act: die with the parent (the kernel's SIGKILL when it
    is killed, as `run`'s workers do; harness/backends/pool.py). Ctrl-C is the parent's
    (the terminal sends SIGINT to the whole group): the worker was born with it blocked,
    and from here on ignores it (so do the processes it starts)."""
    from harness.backends.pool import die_with_parent

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # a Ctrl-C held since its birth is dropped
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    die_with_parent(parent)


@contextlib.contextmanager
def _sigint_held() -> Iterator[None]:
    """SIGINT blocked while the workers are spawned: a spawned interpreter keeps the mask it
    was born with, so a Ctrl-C that reaches a worker still importing (the terminal signals
    the whole group) waits until `_worker_started` ignores it, instead of printing its
    traceback. The parent's own Ctrl-C in that window is held, not lost: recorded by a
    handler of this window (another thread may take the signal), then handed to the
    handler it had before once the window closes: KeyboardInterrupt, or nothing in a
    process that ignores SIGINT (a background job of a shell script). Main thread only."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held: list[int] = []
    previous = signal.signal(signal.SIGINT, lambda signum, _frame: held.append(signum))
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)
    if held and previous is not signal.SIG_IGN:
        if callable(previous):
            previous(signal.SIGINT, None)  # Python's default_int_handler raises KeyboardInterrupt
        else:
            raise KeyboardInterrupt


def _stop_workers(pool: Any) -> None:
    """Kill the pool's worker processes, and whatever they started, now: shutdown() alone
    would wait for the ranges they are running (minutes) after an error, Ctrl-C or
    SIGTERM. ProcessPoolExecutor keeps its processes in `_processes`; Python 3.14's
    kill_workers is the fallback where that is gone (it kills the workers only)."""
    from harness.backends.pool import kill_tree

    processes = getattr(pool, "_processes", None)
    if processes is None:
        kill = getattr(pool, "kill_workers", None)
        if callable(kill):
            kill()
        return
    for process in list(processes.values()):
        if process.pid is not None:
            kill_tree(process.pid)


def collect_in_processes(
    run_job: Callable[..., Any],
    resolved: ResolvedRun,
    jobs: list[Job],
    action_noise: float,
    tick: Callable[[bool], None] | None,
    workers: int,
) -> list[Any]:
    """`jobs` (episode ranges) on `workers` spawned processes, each range's result by
    `run_job(resolved, job, action_noise, tick)` (harness/collect.py's `_collect_job`,
    sent by reference), in the order of `jobs`."""
    from concurrent.futures import FIRST_EXCEPTION, ProcessPoolExecutor, wait
    from concurrent.futures.process import BrokenProcessPool
    from multiprocessing import get_context

    results: list[Any] = [None] * len(jobs)
    pins = checkpoint_pins(resolved)
    context = get_context("spawn")
    pool = ProcessPoolExecutor(workers, context, initializer=_worker_started, initargs=(os.getpid(),))
    try:
        with _sigint_held():  # the workers start during the first submits, and inherit it
            pending = {
                pool.submit(_worker_job, run_job, job, action_noise, resolved.config, pins, workers): n
                for n, job in enumerate(jobs)
            }
        while pending:
            finished, _ = wait(pending, return_when=FIRST_EXCEPTION)
            for future in finished:
                n = pending.pop(future)
                results[n] = future.result()  # a job's error stops the collection here
                for demo in results[n].episodes:
                    if tick:
                        tick(demo.success)
    except BrokenProcessPool as exc:
        raise HarnessError(
            f"a collection worker process died ({exc}; the out-of-memory killer, a kill, or a "
            "crash); nothing was written"
        ) from None
    except BaseException:  # an error, Ctrl-C or SIGTERM: the workers stop now, nothing is written
        _stop_workers(pool)
        raise
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
    return [r for r in results if r is not None]
