"""The scheduler (harness/backends/scheduler.py) against workers that live in this process
and say what a script tells them, on a clock of their own: each rule (retries, a lost or
stalled batch given back, a warm-up's timeout, an outcome handed on once) in
milliseconds. tests/test_backends.py shows the same rules with real processes and faults.
"""

from __future__ import annotations

from collections.abc import Callable
from types import SimpleNamespace
from typing import Any

import pytest

from harness.backends import Execution, scheduler
from harness.backends.scheduler import Event, JobId, job_id, schedule
from harness.errors import HarnessError

Say = tuple[float, str, Any]  # seconds after it is asked, the event's kind (as sent), payload
Script = Callable[[str, list[JobId], bool], list[Say]]  # worker id, group, alone -> what it says


def ready_at_once(worker_id: str) -> list[Say]:
    return [(0.0, "ready", {"host": "h", "worker_id": worker_id})]


def runs_each(worker_id: str, group: list[JobId], alone: bool) -> list[Say]:
    """A worker that runs what it is sent, a second an episode, as a batch says it."""
    if alone:
        return [(1.0, "done", (group[0], f"{worker_id} ran it"))]
    says: list[Say] = [(0.0, "started", jid) for jid in group]
    return says + [(1.0, "done", (jid, f"{worker_id} ran it")) for jid in group]


class ScriptedWorkers:
    """The `Workers` protocol in this process: a started worker says what `warm_up` gives,
    a worker sent a group what `script` gives, each event when the clock reaches it. The
    clock moves only in `wait`: to the next event, or by the whole timeout when none is
    due by then. A killed worker says nothing more; a lost one says what its script says."""

    def __init__(self, script: Script = runs_each, warm_up: Callable[[str], list[Say]] = ready_at_once):
        self.script, self.warm_up = script, warm_up
        self.now = 0.0
        self.worker: dict[int, str] = {}  # slot -> its worker's id
        self.started: list[str] = []
        self.sent: list[tuple[str, list[JobId], bool]] = []
        self.killed: list[tuple[str, float]] = []  # worker id, when
        self.due: list[tuple[float, int, int, str, Any]] = []  # when, order said, slot, kind, payload
        self.waits = 0

    def monotonic(self) -> float:
        return self.now

    def _say(self, slot: int, says: list[Say]) -> None:
        for delay, kind, payload in says:
            self.due.append((self.now + delay, len(self.due), slot, kind, payload))
        self.due.sort()

    def start(self, slot: int) -> str:
        worker_id = f"w{len(self.started)}"
        self.started.append(worker_id)
        self.worker[slot] = worker_id
        self._say(slot, self.warm_up(worker_id))
        return worker_id

    def submit(self, slot: int, group: list[JobId], alone: bool) -> None:
        self.sent.append((self.worker[slot], list(group), alone))
        self._say(slot, self.script(self.worker[slot], list(group), alone))

    def wait(self, timeout: float) -> list[Event]:
        self.waits += 1
        assert self.waits < 10_000, "the scheduler never ended"
        if not self.due or self.due[0][0] > self.now + timeout:
            self.now += max(timeout, 0.001)  # real time moves on while nothing is due
            return []
        self.now = max(self.now, self.due[0][0])
        now = [d for d in self.due if d[0] <= self.now]
        self.due = self.due[len(now) :]
        # read as a transport reads what its worker sent: the kind as sent
        return [Event(slot, kind, payload) for _, _, slot, kind, payload in now]

    def kill(self, slot: int) -> None:
        self.killed.append((self.worker[slot], self.now))
        self.due = [d for d in self.due if d[2] != slot]

    def shutdown(self) -> None:
        pass


def stand_ins(tasks: int, episodes: int, policies: tuple[str, ...] = ("p",)) -> list[Any]:
    """Plan-ordered stand-ins for EpisodeJob (task -> episode -> policy): what the
    scheduler (and units_by_task) reads of them."""
    return [
        SimpleNamespace(
            task=SimpleNamespace(name=f"t{t}"),
            spec=SimpleNamespace(index=e),
            policy=SimpleNamespace(config_id=p),
        )
        for t in range(tasks)
        for e in range(episodes)
        for p in policies
    ]


def run(
    monkeypatch: pytest.MonkeyPatch, jobs: list[Any], transport: ScriptedWorkers, **execution: Any
) -> list[tuple[JobId, Any]]:
    """What the scheduler hands on, in order, with the transport's clock as its own."""
    monkeypatch.setattr(scheduler, "time", SimpleNamespace(monotonic=transport.monotonic))
    done: list[tuple[JobId, Any]] = []

    def hand_on(job: Any, outcome: Any) -> None:
        done.append((job_id(job), outcome))

    schedule(jobs, transport, Execution(**execution), hand_on, lambda _record: None)
    return done


def reason(outcome: Any) -> str | None:
    return outcome.failure_reason if hasattr(outcome, "failure_reason") else None


def test_work_goes_out_task_by_task_with_the_policies_interleaved(monkeypatch):
    jobs = stand_ins(3, 2, ("a", "b"))
    ids = [job_id(j) for j in jobs]
    workers = ScriptedWorkers()
    done = run(monkeypatch, jobs, workers, workers=2)
    assert sorted(jid for jid, _ in done) == sorted(ids)
    # each worker one task, its episodes one at a time in plan order; the third task,
    # whole, to the first worker idle (both at once: the first slot)
    assert workers.sent == [
        ("w0", [ids[0]], True),
        ("w1", [ids[4]], True),
        ("w0", [ids[1]], True),
        ("w1", [ids[5]], True),
        ("w0", [ids[2]], True),
        ("w1", [ids[6]], True),
        ("w0", [ids[3]], True),
        ("w1", [ids[7]], True),
        ("w0", [ids[8]], True),
        ("w0", [ids[9]], True),
        ("w0", [ids[10]], True),
        ("w0", [ids[11]], True),
    ]


def test_a_lost_episode_is_run_again_then_a_failure_row_after_max_retries(monkeypatch):
    jobs = stand_ins(1, 2)
    first, second = (job_id(j) for j in jobs)

    def script(worker_id: str, group: list[JobId], alone: bool) -> list[Say]:
        if group == [first]:
            return [(1.0, "lost", "killed by SIGKILL (the out-of-memory killer, or a kill)")]
        return runs_each(worker_id, group, alone)

    workers = ScriptedWorkers(script)
    done = run(monkeypatch, jobs, workers, workers=1, max_retries=2)
    # the same slot runs it again on a fresh worker, then its next episode
    assert workers.sent == [
        ("w0", [first], True),
        ("w1", [first], True),
        ("w2", [first], True),
        ("w3", [second], True),
    ]
    assert [jid for jid, _ in done] == [first, second]
    row = done[0][1]
    assert row.failure_reason == (
        "worker lost: killed by SIGKILL (the out-of-memory killer, or a kill) (tried 3 times)"
    )
    assert (row.worker_id, row.host, row.success) == ("w2", "h", False)
    assert done[1][1] == "w3 ran it"
    assert workers.killed == []  # lost, not killed


def test_a_lost_batch_runs_what_it_held_alone_without_counting_a_try(monkeypatch):
    jobs = stand_ins(1, 4)
    ids = [job_id(j) for j in jobs]
    runs_alone: list[str] = []

    def script(worker_id: str, group: list[JobId], alone: bool) -> list[Say]:
        if worker_id == "w0":  # 0 ends, 1 and 2 are held, 3 not started when it is lost
            return [
                (1.0, "started", ids[0]),
                (1.0, "started", ids[1]),
                (2.0, "done", (ids[0], "w0 ran it")),
                (2.0, "started", ids[2]),
                (3.0, "lost", "crashed with SIGSEGV (a segmentation fault)"),
            ]
        if alone and group == [ids[1]] and ids[1] not in runs_alone:
            runs_alone.append(ids[1])
            return [(1.0, "lost", "crashed with SIGSEGV (a segmentation fault)")]  # alone: counted
        return runs_each(worker_id, group, alone)

    workers = ScriptedWorkers(script)
    # one try: had the batch's loss counted, episode 1's loss alone would be its last
    done = run(monkeypatch, jobs, workers, workers=1, batch_envs=2, max_retries=1)
    assert workers.sent == [
        ("w0", ids, False),
        ("w1", [ids[1]], True),  # held, in the order they started
        ("w2", [ids[1]], True),  # lost alone once: run again, as without batching
        ("w2", [ids[2]], True),
        ("w2", [ids[3]], False),  # not started: back to its task's queue, batched
    ]
    assert done == [
        (ids[0], "w0 ran it"),
        (ids[1], "w2 ran it"),
        (ids[2], "w2 ran it"),
        (ids[3], "w2 ran it"),
    ]


def test_a_stalled_batch_is_given_back_and_only_the_episode_that_hangs_times_out(monkeypatch):
    jobs = stand_ins(1, 3)
    ids = [job_id(j) for j in jobs]

    def script(worker_id: str, group: list[JobId], alone: bool) -> list[Say]:
        if worker_id == "w0":  # its batch still moves until 9 s, then hangs
            says: list[Say] = [(1.0, "started", ids[0]), (1.0, "started", ids[1])]
            says += [(2.0, "done", (ids[0], "w0 ran it")), (2.0, "started", ids[2])]
            return [*says, (5.0, "stepped", None), (9.0, "stepped", None)]
        if group == [ids[1]]:
            return []  # hangs alone too
        return runs_each(worker_id, group, alone)

    workers = ScriptedWorkers(script)
    done = run(monkeypatch, jobs, workers, workers=1, batch_envs=3, episode_timeout=10)
    # stalled 10 s after it last said something (9 s), not after its last start or end
    assert [w for w, _ in workers.killed] == ["w0", "w1"]
    assert workers.killed[0][1] == pytest.approx(19.0, abs=0.01)
    assert workers.killed[1][1] == pytest.approx(29.0, abs=0.02)  # 10 s after it started alone
    assert workers.sent == [("w0", ids, False), ("w1", [ids[1]], True), ("w2", [ids[2]], True)]
    assert [jid for jid, _ in done] == ids
    assert done[0][1] == "w0 ran it" and done[2][1] == "w2 ran it"
    assert reason(done[1][1]) == "timeout: ran past --episode-timeout 10 s"
    assert done[1][1].worker_id == "w1"


def test_a_warm_up_past_the_timeout_is_charged_to_the_next_episode_of_its_policy(monkeypatch):
    jobs = stand_ins(1, 2, ("a", "b"))
    a0, b0, a1, b1 = (job_id(j) for j in jobs)

    def warm_up(worker_id: str) -> list[Say]:
        says: list[Say] = [(0.0, "warming", "a"), (1.0, "warming", "b")]
        if worker_id == "w0":
            return says  # hangs on b's first call
        return [*says, (2.0, "ready", {"host": "h"})]

    workers = ScriptedWorkers(warm_up=warm_up)
    done = run(monkeypatch, jobs, workers, workers=1, episode_timeout=10)
    assert [w for w, _ in workers.killed] == ["w0"]
    assert workers.killed[0][1] == pytest.approx(11.0, abs=0.01)  # 10 s after it called b
    assert done[0][0] == b0  # b's next episode, not the task's first
    assert reason(done[0][1]) == "timeout: its policy's warm-up call ran past --episode-timeout 10 s"
    assert (done[0][1].worker_id, done[0][1].host) == ("w0", "")  # never ready: no host said
    assert workers.sent == [("w1", [a0], True), ("w1", [a1], True), ("w1", [b1], True)]
    assert [jid for jid, _ in done[1:]] == [a0, a1, b1]


def test_an_outcome_that_arrives_after_its_episode_was_run_again_is_handed_on_once(monkeypatch):
    jobs = stand_ins(1, 2)
    first, second = (job_id(j) for j in jobs)

    def script(worker_id: str, group: list[JobId], alone: bool) -> list[Say]:
        if worker_id == "w0":  # lost; its result arrives after the re-run's (2 s), while the next runs
            return [(1.0, "lost", "stopped answering"), (2.5, "done", (first, "late"))]
        return runs_each(worker_id, group, alone)

    workers = ScriptedWorkers(script)
    done = run(monkeypatch, jobs, workers, workers=1)
    assert done == [(first, "w1 ran it"), (second, "w1 ran it")]


def test_workers_lost_before_taking_work_stop_the_run_after_max_retries(monkeypatch):
    workers = ScriptedWorkers(warm_up=lambda worker_id: [(1.0, "lost", "exited with status 1")])
    with pytest.raises(HarnessError) as error:
        run(monkeypatch, stand_ins(1, 2), workers, workers=1, max_retries=2)
    assert str(error.value) == (
        "3 local workers in a row were lost before taking work (last: exited with status 1); "
        "rows recorded before are kept"
    )
    assert workers.started == ["w0", "w1", "w2"]


def test_a_worker_that_cannot_start_stops_the_run(monkeypatch):
    workers = ScriptedWorkers(warm_up=lambda worker_id: [(0.0, "error", "ValueError: no such checkpoint")])
    with pytest.raises(HarnessError) as error:
        run(monkeypatch, stand_ins(1, 2), workers, backend="ray", workers=2)
    assert str(error.value) == "a ray worker could not start: ValueError: no such checkpoint"


def test_an_event_of_an_unknown_kind_stops_the_run_naming_it(monkeypatch):
    # as a transport reads it off a pipe or out of Ray: the kind as the worker sent it
    workers = ScriptedWorkers(warm_up=lambda worker_id: [(0.0, "finished", None)])
    with pytest.raises(
        HarnessError, match=r"a worker sent an event of unknown kind 'finished' \(known: warming, "
    ):
        run(monkeypatch, stand_ins(1, 2), workers, workers=1)


class UnknownAfterReady(ScriptedWorkers):
    """Its first event's kind is replaced, once made, by one the scheduler has no case for."""

    def wait(self, timeout: float) -> list[Event]:
        events = super().wait(timeout)
        for event in events:
            event.kind = "finished"  # type: ignore[assignment]
        return events


def test_the_scheduler_refuses_an_event_kind_it_has_no_case_for(monkeypatch):
    with pytest.raises(HarnessError, match=r"unknown kind 'finished'"):
        run(monkeypatch, stand_ins(1, 2), UnknownAfterReady(), workers=1)


def test_timed_out_and_lost_rows_record_what_the_worker_last_said_it_had_done(monkeypatch):
    from harness.episode.outcome import Progress

    jobs = stand_ins(1, 3)
    ids = [job_id(j) for j in jobs]
    far = Progress(
        steps=12, chunks=3, nfe_total=30, action_tokens_total=96, policy_time_s=0.6, env_time_s=0.2
    )

    def script(worker_id: str, group: list[JobId], alone: bool) -> list[Say]:
        if group == [ids[1]]:  # says how far it got at 4 s, then hangs
            return [
                (2.0, "stepped", ((ids[1], Progress(steps=4, chunks=1)),)),
                (4.0, "stepped", ((ids[1], far),)),
            ]
        if group == [ids[2]]:  # says how far it got, then its worker is lost
            return [(1.0, "stepped", ((ids[2], far),)), (3.0, "lost", "killed by SIGKILL")]
        return runs_each(worker_id, group, alone)

    workers = ScriptedWorkers(script)
    done = dict(run(monkeypatch, jobs, workers, workers=1, episode_timeout=10, max_retries=0))
    timed_out, lost = done[ids[1]], done[ids[2]]
    assert reason(timed_out) == "timeout: ran past --episode-timeout 10 s"
    assert reason(lost).startswith("worker lost: killed by SIGKILL")
    for row in (timed_out, lost):
        assert (row.steps, row.chunks, row.nfe_total, row.action_tokens_total) == (12, 3, 30, 96)
        assert (row.policy_time_s, row.env_time_s) == (0.6, 0.2)
    assert timed_out.wall_clock_s == pytest.approx(10.0, abs=0.01)  # from its start to its timeout
    assert lost.wall_clock_s == pytest.approx(3.0, abs=0.01)
