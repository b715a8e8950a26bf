"""Hands episodes to workers (processes or Ray actors) and takes back what they return.

Work goes out task by task: a worker takes a task's episodes (every policy, interleaved
episode by episode as in one process, so the policies' timing ratios are taken under
the same load) and keeps that task's env between them. A worker holds one episode at a
time; what it held when it was lost (killed by a signal, a simulator segfault, the
kernel's out-of-memory killer, an exit) is run again on a fresh worker, up to
`max_retries` times, then recorded as a failure row saying why. An episode past
`episode_timeout` is a failure row with reason `timeout: ...` and its worker is replaced.
Every outcome comes back here, to the one process that writes the run folder, and an
episode whose outcome was already handed on is never handed on twice.

The transports (harness/backends/pool.py, ray.py) implement `Workers`: start a worker in
a slot, submit an episode, wait for events, kill a slot's worker.
"""

from __future__ import annotations

import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Any, Protocol

from harness.backends.local import failure_outcome
from harness.episode import EpisodeOutcome
from harness.errors import HarnessError

if TYPE_CHECKING:
    from harness.backends import Execution
    from harness.config import ResolvedRun
    from harness.runner import EpisodeJob

JobId = tuple[str, int, str]  # task name, episode index, policy_config_id
POLL_S = 0.5


def job_id(job: EpisodeJob) -> JobId:
    """What a worker is sent: its own ResolvedRun holds the task, spec and policy."""
    return (job.task.name, job.spec.index, job.policy.config_id)


def index_jobs(resolved: ResolvedRun) -> dict[JobId, EpisodeJob]:
    """Every episode of a (re)built ResolvedRun by its JobId (in a worker)."""
    from harness.runner import plan

    return {job_id(job): job for job in plan(resolved)}


@dataclass
class Event:
    slot: int
    kind: str  # "ready" (payload: the worker's record), "done" ((JobId, outcome)),
    # "lost" (why the worker is gone), "error" (why it could not start)
    payload: Any = None


class Workers(Protocol):
    def start(self, slot: int) -> str: ...  # returns the new worker's id
    def submit(self, slot: int, job: JobId) -> None: ...
    def wait(self, timeout: float) -> list[Event]: ...
    def kill(self, slot: int) -> None: ...
    def shutdown(self) -> None: ...


@dataclass
class Slot:
    worker_id: str = ""
    host: str = ""
    ready: bool = False
    unit: deque[JobId] = field(default_factory=deque)
    inflight: JobId | None = None
    since: float = 0.0  # monotonic time the episode in flight was sent
    started_at: datetime | None = None
    start_failures: int = 0  # workers lost in a row before reporting ready


def units_by_task(jobs: list[EpisodeJob]) -> deque[deque[JobId]]:
    """Consecutive jobs of one task (plan order: episode -> policy) as one unit of work."""
    units: deque[deque[JobId]] = deque()
    last = None
    for job in jobs:
        if job.task.name != last:
            units.append(deque())
            last = job.task.name
        units[-1].append(job_id(job))
    return units


def failure(reason: str, slot: Slot) -> EpisodeOutcome:
    """The row of an episode whose worker did not return it."""
    return failure_outcome(reason, slot.started_at, host=slot.host, worker_id=slot.worker_id)


def schedule(
    jobs: list[EpisodeJob],
    workers: Workers,
    execution: Execution,
    on_done: Callable[[EpisodeJob, EpisodeOutcome], None],
    on_worker: Callable[[dict[str, Any]], None],
) -> None:
    by_id = {job_id(job): job for job in jobs}
    units = units_by_task(jobs)
    slots = [Slot() for _ in range(min(execution.workers, len(units)))]
    attempts: Counter[JobId] = Counter()
    handed_on: set[JobId] = set()

    def hand_on(jid: JobId, outcome: EpisodeOutcome) -> None:
        if jid in handed_on:
            return  # a lost worker's result that arrived after the episode was re-run
        handed_on.add(jid)
        on_done(by_id[jid], outcome)

    def restart(i: int) -> None:
        slot = slots[i]
        slot.ready, slot.inflight, slot.started_at = False, None, None
        if slot.unit or units:
            slot.worker_id = workers.start(i)

    for i, slot in enumerate(slots):
        slot.worker_id = workers.start(i)
    while True:
        for i, slot in enumerate(slots):
            if not slot.ready or slot.inflight is not None:
                continue
            if not slot.unit and units:
                slot.unit = units.popleft()
            if slot.unit:
                slot.inflight = slot.unit.popleft()
                slot.since, slot.started_at = time.monotonic(), datetime.now(UTC)
                workers.submit(i, slot.inflight)
        if not units and all(s.inflight is None and not s.unit for s in slots):
            return
        timeout = POLL_S
        if execution.episode_timeout is not None:
            deadlines = [s.since + execution.episode_timeout for s in slots if s.inflight is not None]
            timeout = min([timeout, *(max(0.0, d - time.monotonic()) for d in deadlines)])
        for event in workers.wait(timeout):
            slot = slots[event.slot]
            if event.kind == "ready":
                slot.ready, slot.start_failures = True, 0
                slot.host = event.payload.get("host", "")
                on_worker(event.payload)
            elif event.kind == "done":
                jid, outcome = event.payload
                if jid == slot.inflight:
                    slot.inflight = None
                hand_on(jid, outcome)
            elif event.kind == "error":
                raise HarnessError(f"a {execution.backend} worker could not start: {event.payload}")
            elif event.kind == "lost":
                jid = slot.inflight
                if jid is None:
                    slot.start_failures += 1
                    if slot.start_failures > execution.max_retries:
                        raise HarnessError(
                            f"{slot.start_failures} {execution.backend} workers in a row were lost "
                            f"before taking work (last: {event.payload}); rows recorded before are kept"
                        )
                else:
                    attempts[jid] += 1
                    if attempts[jid] > execution.max_retries:
                        reason = f"worker lost: {event.payload} (tried {attempts[jid]} times)"
                        hand_on(jid, failure(reason, slot))
                    else:
                        slot.unit.appendleft(jid)  # the same worker slot runs it again
                restart(event.slot)
        if execution.episode_timeout is not None:
            now = time.monotonic()
            for i, slot in enumerate(slots):
                if slot.inflight is not None and now - slot.since > execution.episode_timeout:
                    workers.kill(i)
                    limit = execution.episode_timeout
                    hand_on(slot.inflight, failure(f"timeout: ran past --episode-timeout {limit:g} s", slot))
                    restart(i)
