"""Hands episodes to workers (processes or Ray actors) and takes back what they return.

Work goes out task by task: a worker takes a task's episodes (every policy, interleaved
episode by episode as in one process, so the policies' timing ratios are taken under
the same load) and keeps that task's env between them. With fewer tasks than workers a
task's episodes are split into contiguous ranges, one per idle worker (units_by_task).
Unbatched, a worker holds one episode at a time; what it held when it was lost (killed by a signal, a simulator
segfault, the kernel's out-of-memory killer, an exit) is run again on a fresh worker, up
to `max_retries` times, then recorded as a failure row saying why. An episode past
`episode_timeout` is a failure row with reason `timeout: ...` and its worker is replaced.
Such a row records what the episode had done as its worker last said (a worker reports
its running episodes' steps, chunks, NFE and times every quarter second) and the wall
clock it held the worker, not zeros.
A worker's warm-up (each policy's first calls, before it reports ready) is held to the
same limit, policy by policy: past it the worker is replaced and the next episode of the
policy it was calling gets the `timeout` row (`warm_up_victim`), so a policy that hangs on
every call ends the run with timeout rows instead of hanging it.
Every outcome comes back here, to the one process that writes the run folder, and an
episode whose outcome was already handed on is never handed on twice.

With --batch-envs K a worker is sent a task's episodes of one policy as one group (a
batch serves one policy; the task's policies follow one another, as in one process),
runs them K at a time (harness/episode/loop.py) and says when each starts and ends, so its
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
a slot, submit a group of episodes, wait for events, kill a slot's worker. What a worker
says is an `Event` of an `EventKind`, sent as the kind's string value and read back into
the enum on receipt, so a kind no worker sends stops the run naming it.

The `Scheduler` keeps a `Slot` per worker and loops: hand each idle slot its next group
(`next_group`), wait for events (at most until the nearest deadline), hear each with the
method of its kind, then replace the workers past their deadline. A slot's `SlotState`
is what its worker is doing, so what a loss or a deadline means for the episodes it
held (`Scheduler.lost`, `Scheduler.time_out`):

    STARTING --warming--> WARMING --ready--> IDLE --a group--> RUNNING_ALONE or RUNNING_BATCH
    RUNNING_ALONE / RUNNING_BATCH --its last episode ends--> IDLE
    any --lost, or killed past its deadline--> STARTING (a fresh worker), or
        STOPPED when no work is left for one

- STARTING: building, not yet calling a policy: no deadline (a build is no episode's time).
- WARMING: a policy's warm-up calls; past the limit from the call, `warm_up_victim`. Lost
  here, in STARTING or in IDLE, it counts as a worker lost before taking work:
  `max_retries` of those in a row stop the run.
- IDLE: ready, holding nothing: it is sent its next group at once.
- RUNNING_ALONE: one episode; lost, a try is counted; past the limit from its start, its
  `timeout` row.
- RUNNING_BATCH: a group, K at a time; lost, or past the limit from the last thing it
  said, `Slot.give_back`.
- STOPPED: no worker; no work was left for one.
"""

from __future__ import annotations

import time
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from enum import Enum
from typing import TYPE_CHECKING, Any, Protocol

from harness.backends.jobs import EpisodeJob, JobId, job_id
from harness.episode.loop import EpisodeEvent
from harness.episode.outcome import EpisodeOutcome, Progress, failure_outcome
from harness.errors import HarnessError

if TYPE_CHECKING:
    from harness.backends import Execution

POLL_S = 0.5


class EventKind(Enum):
    """What a worker says; the value is what it sends (a string, across a pipe or Ray)."""

    WARMING = "warming"  # payload: the policy_config_id it calls next, for its warm-up
    READY = "ready"  # the worker's record (host, pid, threads, warm-up)
    # what the episode loop says (harness/episode/loop.py EpisodeEvent), forwarded by a worker:
    STARTED = EpisodeEvent.STARTED.value  # the JobId of an episode its batch started (batched only)
    STEPPED = EpisodeEvent.STEPPED.value  # ((JobId, Progress), ...): its episodes still move, this far
    DONE = EpisodeEvent.DONE.value  # (JobId, outcome)
    LOST = "lost"  # why the worker is gone
    ERROR = "error"  # why it could not start


def unknown_kind(kind: object) -> HarnessError:
    known = ", ".join(k.value for k in EventKind)
    return HarnessError(f"a worker sent an event of unknown kind {kind!r} (known: {known})")


@dataclass
class Event:
    """One thing a slot's worker said. A transport may give `kind` as the string it
    received: it is read into the enum here, where an unknown one stops the run, since
    a kind nothing handles would leave its episodes held forever."""

    slot: int
    kind: EventKind
    payload: Any = None

    def __post_init__(self) -> None:
        if not isinstance(self.kind, EventKind):
            try:
                self.kind = EventKind(self.kind)
            except ValueError:
                raise unknown_kind(self.kind) from None


class Workers(Protocol):
    def start(self, slot: int) -> str: ...  # returns the new worker's id
    def submit(self, slot: int, group: list[JobId], alone: bool) -> None: ...
    def wait(self, timeout: float) -> list[Event]: ...
    def kill(self, slot: int) -> None: ...
    def shutdown(self) -> None: ...


class SlotState(Enum):
    """What a slot's worker is doing (the module docstring has the transitions)."""

    STARTING = "starting"
    WARMING = "warming up"
    IDLE = "idle"
    RUNNING_ALONE = "running alone"
    RUNNING_BATCH = "running a batch"
    STOPPED = "stopped"


NOT_READY = frozenset({SlotState.STARTING, SlotState.WARMING, SlotState.STOPPED})
RUNNING = frozenset({SlotState.RUNNING_ALONE, SlotState.RUNNING_BATCH})


@dataclass
class Slot:
    """A place for one worker at a time, and the work it keeps across its workers: the
    task it took up, and the episodes to run alone on its next worker."""

    worker_id: str = ""
    host: str = ""
    state: SlotState = SlotState.STARTING
    unit: deque[JobId] = field(default_factory=deque)  # the task's episodes not yet sent
    solo: deque[JobId] = field(default_factory=deque)  # to run alone next (lost in a batch)
    held: dict[JobId, tuple[float, datetime]] = field(default_factory=dict)  # started, not back
    progress: dict[JobId, Progress] = field(default_factory=dict)  # how far held ones got, as last said
    queued: list[JobId] = field(default_factory=list)  # sent in a batch, not started
    heard: float = 0.0  # monotonic time the worker last said something
    warming: str | None = None  # the policy (config id) a WARMING worker calls
    warming_since: float = 0.0
    start_failures: int = 0  # workers lost in a row before taking work

    @property
    def ready(self) -> bool:
        return self.state not in NOT_READY

    @property
    def busy(self) -> bool:
        return bool(self.held or self.queued)

    @property
    def has_work(self) -> bool:
        return bool(self.busy or self.unit or self.solo)

    def restart(self, worker_id: str) -> None:
        self.worker_id, self.state = worker_id, SlotState.STARTING

    def lose(self) -> None:
        """Its worker is gone (lost, or killed past its deadline) and what it held was
        dealt with: rows handed on, or episodes put back to run again."""
        self.state, self.warming = SlotState.STOPPED, None
        self.held, self.queued, self.progress = {}, [], {}

    def submit(self, group: list[JobId], alone: bool, now: float) -> None:
        self.heard = now
        if alone:  # an episode sent alone starts at once
            self.state = SlotState.RUNNING_ALONE
            self.held = {jid: (now, datetime.now(UTC)) for jid in group}
        else:  # a batch's episodes are held from when it says they start
            self.state = SlotState.RUNNING_BATCH
            self.queued = list(group)

    def hear_warming(self, policy: str, now: float) -> None:
        """Each policy's warm-up is held to the limit from its own first call."""
        if not self.ready:
            self.state, self.warming, self.warming_since = SlotState.WARMING, policy, now

    def hear_ready(self, host: str) -> None:
        """A worker that got this far ends the run of workers lost before taking work."""
        if not self.busy:
            self.state = SlotState.IDLE
        self.start_failures, self.warming, self.host = 0, None, host

    def hear_started(self, jid: JobId, now: float) -> None:
        if jid in self.queued:
            self.queued.remove(jid)
            self.held[jid] = (now, datetime.now(UTC))

    def hear_stepped(self, progress: tuple[tuple[JobId, Progress], ...] | None) -> None:
        """How far its running episodes have got (None from a worker that does not say)."""
        for jid, done in progress or ():
            if jid in self.held:
                self.progress[jid] = done

    def hear_done(self, jid: JobId) -> None:
        """Also of an episode it no longer holds (one already timed out or re-run)."""
        self.held.pop(jid, None)
        self.progress.pop(jid, None)
        if jid in self.queued:
            self.queued.remove(jid)
        if self.state in RUNNING and not self.busy:
            self.state = SlotState.IDLE

    def give_back(self, batch_envs: int) -> None:
        """A lost or stalled batch: what it held runs alone, what it had not started
        goes back to the front of its task's queue; no try is counted. Having heard of no
        start, the first K episodes not finished are taken as held: a worker starts a
        group's episodes in order, K at once, and a worker may die before its first event
        arrives (a Ray without generator backpressure drops an actor's last events), so
        without this a crash that always strikes first would be sent again forever."""
        held = sorted(self.held, key=lambda jid: self.held[jid][0])
        queued = self.queued
        if not held:
            held, queued = queued[:batch_envs], queued[batch_envs:]
        self.solo.extend(held)
        self.unit.extendleft(reversed(queued))

    def deadline(self, limit: float | None) -> float | None:
        """When its worker is replaced unless it says more (None: never). Alone, an
        episode's own time counts; a batch only has to show it still moves."""
        if limit is None:
            return None
        if self.state is SlotState.WARMING:
            return self.warming_since + limit  # a policy's first calls, in its warm-up
        if self.state is SlotState.RUNNING_ALONE and self.held:
            return min(t for t, _ in self.held.values()) + limit
        if self.state is SlotState.RUNNING_BATCH:
            return self.heard + limit
        return None

    def failure(self, reason: str, jid: JobId | None = None) -> EpisodeOutcome:
        """The row of an episode its worker did not return: its steps, chunks, NFE and
        times as the worker last said (at most PROGRESS_S before), its wall clock from
        its start to now (nothing counted for one that never started: a warm-up's victim)."""
        if jid is None or jid not in self.held:
            return failure_outcome(reason, None, host=self.host, worker_id=self.worker_id)
        started, started_at = self.held[jid]
        return failure_outcome(
            reason,
            started_at,
            host=self.host,
            worker_id=self.worker_id,
            progress=self.progress.get(jid),
            wall_clock_s=time.monotonic() - started,
        )


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


class Scheduler:
    """One run's episodes on `workers`: the hand-out loop, and what each event and each
    deadline does to a slot and to the episodes it held."""

    def __init__(
        self,
        jobs: list[EpisodeJob],
        workers: Workers,
        execution: Execution,
        on_done: Callable[[EpisodeJob, EpisodeOutcome], None],
        on_worker: Callable[[dict[str, Any]], None],
    ):
        self.by_id = {job_id(job): job for job in jobs}
        self.units = units_by_task(jobs, execution.workers)
        self.slots = [Slot() for _ in range(min(execution.workers, len(self.units)))]
        self.workers, self.execution = workers, execution
        self.on_done, self.on_worker = on_done, on_worker
        self.limit = execution.episode_timeout
        self.attempts: Counter[JobId] = Counter()  # losses of an episode run alone
        self.handed_on: set[JobId] = set()

    def run(self) -> None:
        for i, slot in enumerate(self.slots):
            slot.restart(self.workers.start(i))
        while True:
            self.hand_out()
            if not self.units and not any(slot.has_work for slot in self.slots):
                return
            for event in self.workers.wait(self.wait_s()):
                self.hear(event)
            self.time_out_overdue()

    def hand_out(self) -> None:
        """Each idle slot its next group, slot by slot (`next_group`)."""
        for i, slot in enumerate(self.slots):
            if slot.state is not SlotState.IDLE:
                continue
            work = next_group(slot, self.units, self.execution.batch_envs)
            if work is None:
                continue
            group, alone = work
            slot.submit(group, alone, time.monotonic())
            self.workers.submit(i, group, alone)

    def wait_s(self) -> float:
        """Until the nearest deadline, at most POLL_S."""
        deadlines = [d for d in (slot.deadline(self.limit) for slot in self.slots) if d is not None]
        return min([POLL_S, *(max(0.0, d - time.monotonic()) for d in deadlines)])

    def hear(self, event: Event) -> None:
        """Whatever a worker says shows it alive: a batch's deadline moves on with it."""
        self.slots[event.slot].heard = time.monotonic()
        match event.kind:
            case EventKind.WARMING:
                self.warming(event.slot, event.payload)
            case EventKind.READY:
                self.ready(event.slot, event.payload)
            case EventKind.STARTED:
                self.started(event.slot, event.payload)
            case EventKind.STEPPED:
                self.stepped(event.slot, event.payload)
            case EventKind.DONE:
                self.done(event.slot, event.payload)
            case EventKind.LOST:
                self.lost(event.slot, event.payload)
            case EventKind.ERROR:
                self.error(event.slot, event.payload)
            case _:
                raise unknown_kind(event.kind)

    def warming(self, i: int, policy: str) -> None:
        slot = self.slots[i]
        slot.hear_warming(policy, slot.heard)

    def ready(self, i: int, record: dict[str, Any]) -> None:
        self.slots[i].hear_ready(record.get("host", ""))
        self.on_worker(record)

    def started(self, i: int, jid: JobId) -> None:
        slot = self.slots[i]
        slot.hear_started(jid, slot.heard)

    def stepped(self, i: int, progress: tuple[tuple[JobId, Progress], ...] | None) -> None:
        """A batch that still moves was heard (`hear`), so its deadline moved; and how far
        the slot's episodes have got is kept for their rows, should the worker be lost."""
        self.slots[i].hear_stepped(progress)

    def done(self, i: int, payload: tuple[JobId, EpisodeOutcome]) -> None:
        jid, outcome = payload
        self.slots[i].hear_done(jid)
        self.hand_on(jid, outcome)

    def error(self, i: int, why: str) -> None:
        raise HarnessError(f"a {self.execution.backend} worker could not start: {why}")

    def lost(self, i: int, why: str) -> None:
        slot = self.slots[i]
        if slot.state is SlotState.RUNNING_ALONE:
            self.retry(slot, why)
        elif slot.state is SlotState.RUNNING_BATCH:
            slot.give_back(self.execution.batch_envs)  # no try counted (module docstring)
        else:
            slot.start_failures += 1
            if slot.start_failures > self.execution.max_retries:
                raise HarnessError(
                    f"{slot.start_failures} {self.execution.backend} workers in a row were lost "
                    f"before taking work (last: {why}); rows recorded before are kept"
                )
        self.replace(i)

    def retry(self, slot: Slot, why: str) -> None:
        """The episode a worker held alone when it was lost: a try counted against it;
        the same slot runs it again first, or past max_retries it is a failure row."""
        for jid in slot.held:
            self.attempts[jid] += 1
            if self.attempts[jid] > self.execution.max_retries:
                reason = f"worker lost: {why} (tried {self.attempts[jid]} times)"
                self.hand_on(jid, slot.failure(reason, jid))
            else:
                slot.solo.appendleft(jid)

    def time_out_overdue(self) -> None:
        now = time.monotonic()
        for i, slot in enumerate(self.slots):
            due = slot.deadline(self.limit)
            if due is None or now <= due:
                continue
            self.workers.kill(i)
            self.time_out(slot)
            self.replace(i)

    def time_out(self, slot: Slot) -> None:
        """A worker killed past its deadline (only WARMING and running slots have one)."""
        if slot.state is SlotState.WARMING:  # charged to an episode of the policy it called
            jid = warm_up_victim(slot, self.units, str(slot.warming))
            if jid is not None:
                reason = f"timeout: its policy's warm-up call ran past --episode-timeout {self.limit:g} s"
                self.hand_on(jid, slot.failure(reason))
        elif slot.state is SlotState.RUNNING_ALONE:
            for jid in slot.held:
                reason = f"timeout: ran past --episode-timeout {self.limit:g} s"
                self.hand_on(jid, slot.failure(reason, jid))
        else:  # a stalled batch
            slot.give_back(self.execution.batch_envs)

    def replace(self, i: int) -> None:
        """A fresh worker in a slot whose worker is gone, if work is left for one."""
        slot = self.slots[i]
        slot.lose()
        if slot.has_work or self.units:
            slot.restart(self.workers.start(i))

    def hand_on(self, jid: JobId, outcome: EpisodeOutcome) -> None:
        if jid in self.handed_on:
            return  # a lost worker's result that arrived after the episode was re-run
        self.handed_on.add(jid)
        self.on_done(self.by_id[jid], outcome)


def schedule(
    jobs: list[EpisodeJob],
    workers: Workers,
    execution: Execution,
    on_done: Callable[[EpisodeJob, EpisodeOutcome], None],
    on_worker: Callable[[dict[str, Any]], None],
) -> None:
    """Run `jobs` on `workers`, each outcome handed to `on_done` once, each worker's
    record to `on_worker` when it is ready."""
    Scheduler(jobs, workers, execution, on_done, on_worker).run()
