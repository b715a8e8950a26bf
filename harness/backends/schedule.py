"""Hands episodes to workers (processes or Ray actors) and takes back what they return.

Work goes out task by task: a worker takes a task's episodes (every policy, interleaved
episode by episode as in one process, so the policies' timing ratios are taken under
the same load) and keeps that task's env between them. With fewer tasks than workers a
task's episodes are split into contiguous ranges, one per idle worker (units_by_task).
Unbatched, a worker holds one episode at a time; what it held when it was lost (killed by a signal, a simulator
segfault, the kernel's out-of-memory killer, an exit) is run again on a fresh worker, up
to `max_retries` times, then recorded as a failure row saying why. An episode past
`episode_timeout` is a failure row with reason `timeout: ...` and its worker is replaced.
A worker's warm-up (each policy's first calls, before it reports ready) is held to the
same limit, policy by policy: past it the worker is replaced and the next episode of the
policy it was calling gets the `timeout` row (`warm_up_victim`), so a policy that hangs on
every call ends the run with timeout rows instead of hanging it.
Every outcome comes back here, to the one process that writes the run folder, and an
episode whose outcome was already handed on is never handed on twice.

With --batch-envs K a worker is sent a task's episodes of one policy as one group (a
batch serves one policy; the task's policies follow one another, as in one process),
runs them K at a time (harness/batched.py) and says when each starts and ends, so its
rows are written as they end and the parent knows which episodes it holds: up to K.
- A batched worker lost: every episode it held is run again, alone (`alone` groups, one
  episode each, unbatched), on its fresh replacement; no try is counted against them,
  since a batch cannot tell which of its episodes brought the worker down. Run alone,
  the one that does is lost again and counted, as without batching; the others finish.
  Episodes of the group that had not started go back to the task's queue.
- --episode-timeout: an episode in a batch is stretched by its batch-mates (K envs step
  one after another), so its wall time says nothing about it alone, and a hang stops
  every slot at once. A batch is stalled when its worker says nothing (no step of the
  lockstep loop, no start or end) for `episode_timeout` seconds (it says it still moves
  every quarter of that); its worker is then replaced and the episodes it held run
  alone, where the timeout is the episode's as without batching, so only the episode
  that hangs gets the `timeout` row.

The transports (harness/backends/pool.py, ray.py) implement `Workers`: start a worker in
a slot, submit a group of episodes, wait for events, kill a slot's worker.
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
    kind: str  # "warming" (the policy_config_id it calls next, for its warm-up), "ready"
    # (payload: the worker's record), "started" (JobId, batched only),
    # "stepped" (a batch still moves), "done" ((JobId, outcome)), "lost" (why the
    # worker is gone), "error" (why it could not start)
    payload: Any = None


class Workers(Protocol):
    def start(self, slot: int) -> str: ...  # returns the new worker's id
    def submit(self, slot: int, group: list[JobId], alone: bool) -> None: ...
    def wait(self, timeout: float) -> list[Event]: ...
    def kill(self, slot: int) -> None: ...
    def shutdown(self) -> None: ...


@dataclass
class Slot:
    worker_id: str = ""
    host: str = ""
    ready: bool = False
    unit: deque[JobId] = field(default_factory=deque)  # the task's episodes not yet sent
    solo: deque[JobId] = field(default_factory=deque)  # to run alone next (lost in a batch)
    held: dict[JobId, tuple[float, datetime]] = field(default_factory=dict)  # started, not back
    queued: list[JobId] = field(default_factory=list)  # sent in a batch, not started
    alone: bool = False  # the group in flight runs episode by episode
    heard: float = 0.0  # monotonic time the worker last said something of its group
    warming: str | None = None  # the policy (config id) a starting worker is warming up
    warming_since: float = 0.0
    start_failures: int = 0  # workers lost in a row before reporting ready

    @property
    def busy(self) -> bool:
        return bool(self.held or self.queued)

    @property
    def has_work(self) -> bool:
        return bool(self.busy or self.unit or self.solo)


def units_by_task(jobs: list[EpisodeJob], workers: int = 1) -> deque[deque[JobId]]:
    """Consecutive jobs of one task (plan order: episode -> policy) as one unit of work;
    with fewer tasks than workers, the largest unit halved at an episode boundary until
    every worker has one (or no unit holds two episodes). Without that a one-task suite
    (a chain scene, one SimplerEnv task) ran on one worker whatever --workers said. Each
    half keeps every policy's episode together, so the interleaving is unchanged, and
    costs one more env build; episodes are seeded by index, so the rows are the same."""
    units: deque[deque[JobId]] = deque()
    last = None
    for job in jobs:
        if job.task.name != last:
            units.append(deque())
            last = job.task.name
        units[-1].append(job_id(job))
    while units and len(units) < workers:
        at = max(range(len(units)), key=lambda i: len(units[i]))
        episodes = list(dict.fromkeys(jid[1] for jid in units[at]))
        if len(episodes) < 2:
            break
        later = set(episodes[len(episodes) // 2 :])
        largest = units[at]
        units[at] = deque(jid for jid in largest if jid[1] not in later)
        units.insert(at + 1, deque(jid for jid in largest if jid[1] in later))
    return units


def next_group(slot: Slot, units: deque[deque[JobId]], batch_envs: int) -> tuple[list[JobId], bool] | None:
    """What the slot's worker runs next, and whether alone: an episode lost in a batch,
    else the next episode of its task (unbatched), or the task's next policy's episodes
    (batched); a new task when its own is done. None when no work is left for it."""
    if slot.solo:
        return [slot.solo.popleft()], True
    if not slot.unit and units:
        slot.unit = units.popleft()
    if not slot.unit:
        return None
    if batch_envs == 1:
        return [slot.unit.popleft()], True
    policy = slot.unit[0][2]
    group = [jid for jid in slot.unit if jid[2] == policy]
    slot.unit = deque(jid for jid in slot.unit if jid[2] != policy)
    return group, False


def warm_up_victim(slot: Slot, units: deque[deque[JobId]], policy: str) -> JobId | None:
    """The episode charged with a warm-up that ran past --episode-timeout: the next one
    of that policy the slot's worker would have run (taking up a task if it has none).
    Each replacement warms up again, so a policy that hangs on every call gets one
    `timeout` row per episode, each after the limit, and the run ends."""
    if not slot.solo and not slot.unit and units:
        slot.unit = units.popleft()
    for queue in (slot.solo, slot.unit):
        for jid in queue:
            if jid[2] == policy:
                queue.remove(jid)
                return jid
    for queue in (slot.solo, slot.unit):
        if queue:
            return queue.popleft()
    return None


def failure(reason: str, slot: Slot, started_at: datetime | None) -> EpisodeOutcome:
    """The row of an episode whose worker did not return it."""
    return failure_outcome(reason, started_at, host=slot.host, worker_id=slot.worker_id)


def schedule(
    jobs: list[EpisodeJob],
    workers: Workers,
    execution: Execution,
    on_done: Callable[[EpisodeJob, EpisodeOutcome], None],
    on_worker: Callable[[dict[str, Any]], None],
) -> None:
    by_id = {job_id(job): job for job in jobs}
    units = units_by_task(jobs, execution.workers)
    slots = [Slot() for _ in range(min(execution.workers, len(units)))]
    attempts: Counter[JobId] = Counter()
    handed_on: set[JobId] = set()
    limit = execution.episode_timeout

    def hand_on(jid: JobId, outcome: EpisodeOutcome) -> None:
        if jid in handed_on:
            return  # a lost worker's result that arrived after the episode was re-run
        handed_on.add(jid)
        on_done(by_id[jid], outcome)

    def give_back(slot: Slot) -> None:
        """A lost or stalled batch: what it held runs alone, what it had not started
        goes back to the front of its task's queue; no try is counted. Having heard of no
        start, the first K episodes not finished are taken as held: a worker starts a
        group's episodes in order, K at once, and a worker may die before its first event
        arrives (a Ray without generator backpressure drops an actor's last events), so
        without this a crash that always strikes first would be sent again forever."""
        held = sorted(slot.held, key=lambda jid: slot.held[jid][0])
        queued = slot.queued
        if not held:
            held, queued = queued[: execution.batch_envs], queued[execution.batch_envs :]
        slot.solo.extend(held)
        slot.unit.extendleft(reversed(queued))

    def restart(i: int) -> None:
        slot = slots[i]
        slot.ready, slot.alone, slot.warming = False, False, None
        slot.held, slot.queued = {}, []
        if slot.has_work or units:
            slot.worker_id = workers.start(i)

    def deadline(slot: Slot) -> float | None:
        if limit is not None and not slot.ready and slot.warming is not None:
            return slot.warming_since + limit  # a policy's first calls, in its warm-up
        if limit is None or not slot.busy:
            return None
        if slot.alone:
            return min(t for t, _ in slot.held.values()) + limit if slot.held else None
        return slot.heard + limit

    for i, slot in enumerate(slots):
        slot.worker_id = workers.start(i)
    while True:
        for i, slot in enumerate(slots):
            if not slot.ready or slot.busy:
                continue
            work = next_group(slot, units, execution.batch_envs)
            if work is None:
                continue
            group, slot.alone = work
            now = time.monotonic()
            slot.heard = now
            if slot.alone:  # an episode sent alone starts at once
                slot.held = {jid: (now, datetime.now(UTC)) for jid in group}
            else:
                slot.queued = list(group)
            workers.submit(i, group, slot.alone)
        if not units and not any(s.has_work for s in slots):
            return
        timeout = POLL_S
        deadlines = [d for d in map(deadline, slots) if d is not None]
        timeout = min([timeout, *(max(0.0, d - time.monotonic()) for d in deadlines)])
        for event in workers.wait(timeout):
            slot = slots[event.slot]
            slot.heard = time.monotonic()
            if event.kind == "warming":
                slot.warming, slot.warming_since = event.payload, slot.heard
            elif event.kind == "ready":
                slot.ready, slot.start_failures, slot.warming = True, 0, None
                slot.host = event.payload.get("host", "")
                on_worker(event.payload)
            elif event.kind == "started":
                if event.payload in slot.queued:
                    slot.queued.remove(event.payload)
                    slot.held[event.payload] = (slot.heard, datetime.now(UTC))
            elif event.kind == "done":
                jid, outcome = event.payload
                slot.held.pop(jid, None)
                if jid in slot.queued:
                    slot.queued.remove(jid)
                hand_on(jid, outcome)
            elif event.kind == "error":
                raise HarnessError(f"a {execution.backend} worker could not start: {event.payload}")
            elif event.kind == "lost":
                if slot.alone and slot.held:
                    for jid, (_, started_at) in slot.held.items():
                        attempts[jid] += 1
                        if attempts[jid] > execution.max_retries:
                            reason = f"worker lost: {event.payload} (tried {attempts[jid]} times)"
                            hand_on(jid, failure(reason, slot, started_at))
                        else:
                            slot.solo.appendleft(jid)  # the same worker slot runs it again
                elif slot.busy:
                    give_back(slot)
                else:
                    slot.start_failures += 1
                    if slot.start_failures > execution.max_retries:
                        raise HarnessError(
                            f"{slot.start_failures} {execution.backend} workers in a row were lost "
                            f"before taking work (last: {event.payload}); rows recorded before are kept"
                        )
                restart(event.slot)
        now = time.monotonic()
        for i, slot in enumerate(slots):
            due = deadline(slot)
            if due is None or now <= due:
                continue
            workers.kill(i)
            if not slot.ready:  # its warm-up: charged to an episode of the policy it called
                jid = warm_up_victim(slot, units, str(slot.warming))
                if jid is not None:
                    reason = f"timeout: its policy's warm-up call ran past --episode-timeout {limit:g} s"
                    hand_on(jid, failure(reason, slot, None))
            elif slot.alone:
                for jid, (_, started_at) in slot.held.items():
                    reason = f"timeout: ran past --episode-timeout {limit:g} s"
                    hand_on(jid, failure(reason, slot, started_at))
            else:
                give_back(slot)
            restart(i)
