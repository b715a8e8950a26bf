"""Worker processes and Ray actors: the same rows as one process, and faults survived.

Faults are real: a worker process really gets SIGKILL, a segfault (a read of address 0),
an exit, or hangs (tests/fakes.py FaultPolicy), on the physics-free fake suite.
"""

from __future__ import annotations

import importlib.util
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest

from harness.backends import Execution
from harness.backends.jobs import plan_jobs as plan
from harness.backends.local import HOST, Worker
from harness.backends.ray import actor_death_reason
from harness.backends.scheduler import Event, JobId, job_id, schedule, units_by_task
from harness.run.folder import OpenMode
from harness.run.runner import run
from results.schema import PROVENANCE_COLUMNS, TIMING_COLUMNS
from tests.fakes import FakeBuild
from tests.test_schedule import stand_ins

pytestmark = pytest.mark.metaworld  # these tests run Meta-World episodes

REPO = Path(__file__).resolve().parent.parent
HAS_RAY = importlib.util.find_spec("ray") is not None
NEEDS_RAY = pytest.mark.skipif(not HAS_RAY, reason="ray is not installed (pip install 'dvla-harness[ray]')")
# Every test that starts a local Ray cluster stays in this file: tox.ini runs the suite with
# pytest-xdist's --dist loadfile (a file on one worker), so one cluster runs at a time; each
# claims every core (num_cpus), and two at once slow each other's actors towards these
# tests' episode timeouts.


def _rows(report):
    df = report.run_dir.read_episodes()
    return df.sort_values(["task", "episode_index", "policy"]).reset_index(drop=True)


def _same_results(a, b) -> None:
    columns = [c for c in a.columns if c not in TIMING_COLUMNS | PROVENANCE_COLUMNS]
    # values, not dtypes: a nullable int column reads as float where another row of its
    # table is null (a lost worker's row has no counts), as int where none is
    pd.testing.assert_frame_equal(a[columns], b[columns], check_dtype=False)


def test_workers_give_the_rows_of_one_process_and_say_where_they_ran(tmp_path):
    build = FakeBuild(episodes=3, tasks=2)
    alone = run(build(), tmp_path / "one")
    pooled = run(build(), tmp_path / "two", execution=Execution(workers=2, device="auto", rebuild=build))
    a, b = _rows(alone), _rows(pooled)
    assert len(b) == 6 and b["failure_reason"].isna().all()
    _same_results(a, b)
    # (a worker that starts first may take both tasks before the other is up)
    assert set(a["worker_id"]) == {"main"} and set(b["worker_id"]) <= {"local-0", "local-1"}
    assert set(a["host"]) == set(b["host"]) == {HOST}
    # a task's episodes stay with one worker
    assert b.groupby("task")["worker_id"].nunique().eq(1).all()
    session = pooled.run_dir.read_manifest()["execution"][-1]
    assert session["backend"] == "local" and session["workers"] == 2
    # every worker that ran rows is recorded (one still starting when the work ran out is not)
    workers = session["worker_threads"]
    assert set(b["worker_id"]) <= {w["worker_id"] for w in workers} <= {"local-0", "local-1"}
    assert all(w["threads"] == 1 and w["workers"] == 2 and w["pid"] != os.getpid() for w in workers)
    # and where each decoded: --device resolved in the worker (no GPU here: the CPU)
    assert all(w["device"] == {"requested": "auto", "used": "cpu", "gpu": None} for w in workers)
    # each worker warmed its policy up before its first timed episode
    assert all([p["policy"] for p in w["warm_up"]["policies"]] == ["fake"] for w in workers)


def test_a_task_is_split_into_episode_ranges_only_when_workers_would_idle():
    one_task = units_by_task(stand_ins(1, 5, ("a", "b")), workers=2)
    # contiguous episode ranges, every policy's episode kept together, in plan order
    assert [list(u) for u in one_task] == [
        [("t0", 0, "a"), ("t0", 0, "b"), ("t0", 1, "a"), ("t0", 1, "b")],
        [("t0", e, p) for e in (2, 3, 4) for p in ("a", "b")],
    ]
    assert [len(u) for u in units_by_task(stand_ins(1, 8, ("a",)), workers=4)] == [2, 2, 2, 2]
    # as many tasks as workers, or one worker: a task stays whole
    assert [len(u) for u in units_by_task(stand_ins(3, 4, ("a",)), workers=2)] == [4, 4, 4]
    assert len(units_by_task(stand_ins(1, 4, ("a",)), workers=1)) == 1
    # one episode cannot be split; no jobs, no units
    assert len(units_by_task(stand_ins(1, 1, ("a", "b")), workers=4)) == 1
    assert not units_by_task([], workers=4)


@pytest.mark.parametrize("backend", ["local", pytest.param("ray", marks=NEEDS_RAY)])
def test_a_one_task_suite_runs_on_every_worker_with_the_rows_of_one_process(tmp_path, backend):
    build = FakeBuild(episodes=4, delay=0.5)  # slow enough for both workers to start
    alone = run(build(), tmp_path / "one")
    execution = Execution(backend=backend, workers=2, rebuild=build)
    pooled = run(build(), tmp_path / "two", execution=execution)
    a, b = _rows(alone), _rows(pooled)
    assert len(b) == 4 and b["failure_reason"].isna().all()
    _same_results(a, b)
    # both workers ran episodes, each a contiguous range (0-1 and 2-3)
    assert b["worker_id"].nunique() == 2
    by_range = b.sort_values("episode_index").groupby(b["episode_index"] // 2)["worker_id"].nunique()
    assert by_range.eq(1).all()


def test_lost_workers_episodes_are_rerun_then_recorded_as_failures(tmp_path):
    # episode 1 is killed once only, so its retry succeeds; 2 and 3 die every time
    build = FakeBuild(
        faults=((1, "sigkill:once"), (2, "segfault"), (3, "exit")), marks=str(tmp_path), episodes=5
    )
    report = run(build(), tmp_path / "r", execution=Execution(workers=2, max_retries=1, rebuild=build))
    rows = _rows(report).set_index("episode_index")
    assert len(rows) == 5 and report.executed == 5
    assert rows.loc[[0, 1, 4], "success"].all()
    assert rows.loc[2, "failure_reason"].startswith("worker lost: crashed with SIGSEGV")
    assert rows.loc[3, "failure_reason"] == "worker lost: exited with status 3 (tried 2 times)"
    events = [json.loads(line) for line in (tmp_path / "r" / "events.jsonl").read_text().splitlines()]
    assert sum(e["event"] == "episode_failed" for e in events) == 2
    # workers started: one per slot (the one task is split in two; a slot's first worker
    # that is not up before the work runs out is not recorded), then one per loss (1 + 2 + 2)
    assert len(report.run_dir.read_manifest()["execution"][-1]["worker_threads"]) - 5 in (1, 2)


def test_segfault_is_retried_on_a_fresh_worker_until_it_passes(tmp_path):
    build = FakeBuild(faults=((1, "segfault:once"),), marks=str(tmp_path), episodes=2)
    report = run(build(), tmp_path / "r", execution=Execution(workers=2, rebuild=build))
    rows = _rows(report)
    # the one task is split across the two first workers; episode 1 reran on a third
    assert rows["success"].all() and rows["worker_id"].tolist()[1] == "local-2"
    assert rows["worker_id"].tolist()[0] in ("local-0", "local-1")


def test_an_episode_past_the_timeout_is_a_timeout_row_and_its_worker_replaced(tmp_path):
    build = FakeBuild(faults=((1, "hang"),), episodes=3)
    execution = Execution(workers=1, episode_timeout=3.0, rebuild=build)
    start = time.monotonic()
    report = run(build(), tmp_path / "r", execution=execution)
    assert time.monotonic() - start < 60
    rows = _rows(report).set_index("episode_index")
    assert rows.loc[1, "failure_reason"] == "timeout: ran past --episode-timeout 3 s"
    assert rows.loc[[0, 2], "success"].all()
    assert rows.loc[0, "worker_id"] == rows.loc[1, "worker_id"] == "local-0"
    assert rows.loc[2, "worker_id"] == "local-1"


def test_batched_workers_give_the_rows_of_one_batched_process(tmp_path):
    build = FakeBuild(episodes=5, tasks=2, batch=True)
    alone = run(build(), tmp_path / "one", execution=Execution(batch_envs=3))
    pooled = run(build(), tmp_path / "two", execution=Execution(workers=2, batch_envs=3, rebuild=build))
    a, b = _rows(alone), _rows(pooled)
    assert len(b) == 10 and b["failure_reason"].isna().all()
    _same_results(a, b)
    assert set(b["batch_envs"]) == {3} and set(b["worker_id"]) <= {"local-0", "local-1"}
    assert (b["nfe_total"] == b["chunks"]).all()  # one pass per call, charged to each row it served
    assert b.groupby("task")["worker_id"].nunique().eq(1).all()
    assert pooled.run_dir.read_manifest()["execution"][-1]["batch_envs"] == 3
    # --resume with a larger protocol runs only the new episodes, batched in the workers
    bigger = FakeBuild(episodes=6, tasks=2, batch=True)
    execution = Execution(workers=2, batch_envs=3, rebuild=bigger)
    resumed = run(bigger(), tmp_path / "two", OpenMode.RESUME, execution=execution)
    assert (resumed.skipped, resumed.executed) == (10, 2)
    rows = _rows(resumed)
    assert (
        len(rows) == 12
        and set(rows["batch_envs"]) == {3}
        and not rows.duplicated(["task", "episode_index"]).any()
    )


def test_a_batched_worker_warms_up_at_the_batch_shape_and_reports_each_episode():
    worker = Worker(FakeBuild(episodes=4, batch=True)(), "w-0", batch_envs=3, heartbeat_s=0.0)
    policy = worker.runner.resolved.policies[0].policy
    try:
        assert policy.sizes == [] and worker.warm_up is None  # built; warmed up next, step by step
        assert list(worker.warming()) == [("warming", "fakeconfig01")]  # the policy it calls next
        assert policy.sizes == [1, 3]  # warm-up: one act, then one act_batch of 3
        assert worker.warm_up["policies"][0]["error"] is None
        group = sorted(worker.jobs)
        events = list(worker.run(group, alone=False))
        started = [payload for kind, payload in events if kind == "started"]
        done = {payload[0]: payload[1] for kind, payload in events if kind == "done"}
        assert started == group and sorted(done) == group
        assert [kind for kind, _ in events[:3]] == ["started"] * 3  # K slots filled first
        assert "stepped" in [kind for kind, _ in events]  # the heartbeat (every step at 0 s)
        for jid in group:  # an episode is reported started before it is reported done
            assert events.index(("started", jid)) < next(
                n for n, (kind, payload) in enumerate(events) if kind == "done" and payload[0] == jid
            )
        assert all(o.batch_envs == 3 and o.worker_id == "w-0" and o.host == HOST for o in done.values())
        assert max(policy.sizes[2:]) == 3
        quiet = Worker(FakeBuild(episodes=4, batch=True)(), "w-1", batch_envs=3)
        assert "stepped" not in [
            kind for kind, _ in quiet.run(group, alone=False)
        ]  # no timeout: no heartbeat
        quiet.close()
        ((kind, (jid, outcome)),) = worker.run(group[:1], alone=True)  # re-run alone: unbatched
        assert kind == "done" and jid == group[0] and outcome.batch_envs == 1 and outcome.success
    finally:
        worker.close()


def test_a_batched_worker_lost_mid_batch_has_its_episodes_rerun_alone_none_twice(tmp_path):
    # chunks of 2, success at step 5: episodes 0-2 end and are reported, 3-5 start, and
    # the first decode for 3-5 kills the worker (episode 4's fault) with the three in flight
    build = FakeBuild(faults=((4, "sigkill"),), episodes=7, batch=True)
    execution = Execution(workers=2, batch_envs=3, max_retries=1, rebuild=build)
    report = run(build(), tmp_path / "r", execution=execution)
    rows = _rows(report).set_index("episode_index")
    assert len(rows) == 7 and report.executed == 7 and rows.index.is_unique
    # the batch's loss counted against none of them; alone, 4 was lost twice (tries: 1 + 1 retry)
    assert rows.loc[4, "failure_reason"] == (
        "worker lost: killed by SIGKILL (the out-of-memory killer, or a kill) (tried 2 times)"
    )
    assert rows.loc[[0, 1, 2, 3, 5, 6], "success"].all()
    assert rows["batch_envs"].to_dict() == {0: 3, 1: 3, 2: 3, 3: 1, 4: 1, 5: 1, 6: 3}
    clean = _rows(
        run(FakeBuild(episodes=7, batch=True)(), tmp_path / "clean", execution=Execution(batch_envs=3))
    )
    ok = [0, 1, 2, 3, 5, 6]
    a = clean.set_index("episode_index").loc[ok].drop(columns="batch_envs").reset_index()
    _same_results(a, rows.loc[ok].drop(columns="batch_envs").reset_index())
    # workers: one per slot (the task is split in two; one not up before the work runs out
    # is not recorded), one after the batch was lost, one after each loss of 4 alone
    assert len(report.run_dir.read_manifest()["execution"][-1]["worker_threads"]) - 3 in (1, 2)


def test_a_stalled_batch_is_stopped_and_only_the_episode_that_hangs_times_out(tmp_path):
    build = FakeBuild(faults=((4, "hang"),), episodes=6, batch=True)
    execution = Execution(workers=1, batch_envs=3, episode_timeout=3.0, rebuild=build)
    start = time.monotonic()
    report = run(build(), tmp_path / "r", execution=execution)
    assert time.monotonic() - start < 90
    rows = _rows(report).set_index("episode_index")
    assert len(rows) == 6 and rows.index.is_unique
    assert rows.loc[4, "failure_reason"] == "timeout: ran past --episode-timeout 3 s"
    assert rows.loc[[0, 1, 2, 3, 5], "success"].all()
    assert rows["batch_envs"].to_dict() == {0: 3, 1: 3, 2: 3, 3: 1, 4: 1, 5: 1}
    # the stalled batch's worker, then the one that ran 3 and hung on 4 alone, then 5's
    assert rows.loc[[0, 3, 4, 5], "worker_id"].tolist() == ["local-0", "local-1", "local-1", "local-2"]


class _Scripted:
    """A transport whose worker returns episode 0 twice (as a lost worker's late result
    and its re-run would), then the rest."""

    def __init__(self):
        self.sent: list = []
        self.events: list[Event] = [Event(0, "ready", {"host": "h", "worker_id": "w"})]

    def start(self, slot):
        return "w"

    def submit(self, slot, group, alone):
        assert alone and len(group) == 1  # unbatched: one episode at a time
        (job,) = group
        self.sent.append(job)
        self.events.append(Event(slot, "done", (job, f"outcome of {job}")))
        if len(self.sent) == 1:
            self.events.append(Event(slot, "done", (job, "again")))

    def wait(self, timeout):
        events, self.events = self.events, []
        return events

    def kill(self, slot):
        pass

    def shutdown(self):
        pass


def test_an_episode_returned_twice_is_handed_on_once():
    jobs = plan(FakeBuild(episodes=3)())
    done = []
    schedule(jobs, _Scripted(), Execution(workers=1), lambda job, out: done.append((job_id(job), out)), print)
    assert [j for j, _ in done] == [job_id(j) for j in jobs]
    assert "again" not in [out for _, out in done]


class _SilentBatch:
    """A transport whose first batched worker dies before any of its events arrive (as a
    Ray actor's last events may die with it); later workers run what they are sent."""

    def __init__(self) -> None:
        self.sent: list[tuple[list[JobId], bool]] = []
        self.events: list[Event] = [Event(0, "ready", {"host": "h"})]

    def start(self, slot: int) -> str:
        if self.sent:
            self.events.append(Event(slot, "ready", {"host": "h"}))
        return f"w{len(self.sent)}"

    def submit(self, slot: int, group: list[JobId], alone: bool) -> None:
        self.sent.append((list(group), alone))
        if len(self.sent) == 1:
            self.events.append(Event(slot, "lost", "killed"))
            return
        for jid in group:
            self.events += [Event(slot, "started", jid), Event(slot, "done", (jid, f"outcome of {jid}"))]

    def wait(self, timeout: float) -> list[Event]:
        events, self.events = self.events, []
        return events

    def kill(self, slot: int) -> None:
        pass

    def shutdown(self) -> None:
        pass


def test_a_batch_lost_unheard_runs_the_first_k_it_may_have_held_alone():
    jobs = plan(FakeBuild(episodes=5)())
    ids = [job_id(j) for j in jobs]
    done = []
    transport = _SilentBatch()
    execution = Execution(workers=1, batch_envs=2, max_retries=0)
    schedule(jobs, transport, execution, lambda job, out: done.append(job_id(job)), print)
    assert sorted(done) == sorted(ids)  # each once, none counted as a failure
    assert transport.sent == [(ids, False), ([ids[0]], True), ([ids[1]], True), (ids[2:], False)]


KILL_SCRIPT = """
import sys
from pathlib import Path
from harness.backends import Execution
from harness.run.folder import OpenMode
from harness.run.runner import run
from tests.fakes import FakeBuild

if __name__ == "__main__":
    build = FakeBuild(episodes=6, tasks=2, delay=0.15)
    run(build(), Path(sys.argv[1]), execution=Execution(backend=sys.argv[2], workers=2, rebuild=build))
"""


def _running(pid: int) -> bool:
    """Alive and not a zombie waiting to be reaped."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except FileNotFoundError:
        return False
    return "State:\tZ" not in status


@pytest.mark.parametrize("backend", ["local", pytest.param("ray", marks=NEEDS_RAY)])
def test_parent_sigkill_then_resume_records_each_episode_once(tmp_path, backend):
    out = tmp_path / "r"
    script = tmp_path / "go.py"
    script.write_text(KILL_SCRIPT)
    env = os.environ | {"PYTHONPATH": str(REPO)}
    proc = subprocess.Popen([sys.executable, str(script), str(out), backend], cwd=REPO, env=env)
    pending = out / "pending.jsonl"
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None:
        if pending.is_file() and len(pending.read_text().splitlines()) >= 3:
            break
        time.sleep(0.05)
    assert proc.poll() is None, "the run ended before it could be killed"
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    first = len({tuple(json.loads(line).values()) for line in pending.read_text().splitlines()})
    assert 3 <= first < 12
    pids = [
        w["pid"] for w in json.loads((out / "manifest.json").read_text())["execution"][-1]["worker_threads"]
    ]
    # the workers end with their parent: local ones by PR_SET_PDEATHSIG at once, Ray's
    # actors when the local Ray the parent started sees its driver gone (seconds)
    deadline = time.monotonic() + 30
    while [pid for pid in pids if _running(pid)] and time.monotonic() < deadline:
        time.sleep(0.2)
    assert pids and not [pid for pid in pids if _running(pid)]
    build = FakeBuild(episodes=6, tasks=2)
    # resumed in this process: another backend and worker count are not a config difference
    report = run(build(), out, OpenMode.RESUME, execution=Execution(workers=1))
    assert report.skipped == first and report.executed == 12 - first
    episodes = report.run_dir.read_episodes()
    assert len(episodes) == 12 and not episodes.duplicated(["task", "episode_index", "policy"]).any()
    sessions = report.run_dir.read_manifest()["execution"]
    assert [(s["backend"], s["workers"]) for s in sessions] == [(backend, 2), ("local", 1)]


VANISHED = (
    "its process vanished (Ray saw its connection close): crashed (e.g. SIGSEGV), exited, "
    "or killed by SIGKILL (the out-of-memory killer, or a kill); Ray does not say which"
)

# str(exc) of the RayActorError (an ActorDiedError each time) that ray.get raised for a
# call to an actor (max_restarts=0) that died as said, measured with Ray 2.60.0 on Linux
# (2026-11-24, a throwaway script: one local Ray, one actor per case; a streaming
# generator's call said the same). Each message is _DIED_HEAD + the worker's exit detail.
_DIED_HEAD = (
    "The actor died unexpectedly before finishing this task.\n"
    "\tclass_name: A\n"
    "\tactor_id: 1d52329c24585efe12bdc05a01000000\n"
    "\tpid: 7647\n"
    "\tnamespace: 9ed82617-f9a2-4bec-9084-72bd20c0c71d\n"
    "\tip: 192.0.2.2\n"
)
_PROCESS_DIED = "The actor is dead because its worker process has died. Worker exit type: "
# the same for ctypes.string_at(0), os.kill(own pid, SIGSEGV), os._exit(3), os.abort(),
# os.kill(own pid, SIGKILL) and a SIGKILL from outside
_CONNECTION_CLOSED = (
    _PROCESS_DIED
    + "SYSTEM_ERROR Worker exit detail: Worker unexpectedly exits with a connection error code 2. "
    "End of file. Some common causes include: (1) the process was killed by the OOM killer due to high "
    "memory usage, (2) ray stop --force was called, or (3) the worker crashed unexpectedly due to SIGSEGV "
    "or another unexpected error. If the process was killed by the kernel OOM killer (verifiable by "
    "checking for OOM in dmesg of the OOMing node), consider enabling resource isolation via "
    "--enable-resource-isolation to prevent node deaths by resource contention and significant loss of "
    "progress by uninformed kernel OOM killing."
)
_SIGTERM = (  # os.kill(pid, SIGTERM) from outside
    _PROCESS_DIED + "SYSTEM_ERROR Worker exit detail: Worker exits unexpectedly. Worker exits with an exit "
    "code 1. The process receives a SIGTERM."
)
_SYS_EXIT_3 = (  # sys.exit(3) in the actor's method (Python's exit, not os._exit)
    _PROCESS_DIED
    + "SYSTEM_ERROR Worker exit detail: Worker exits unexpectedly. Worker exits with an exit code 3."
)
_EXIT_ACTOR = (  # ray.actor.exit_actor()
    _PROCESS_DIED
    + "INTENDED_USER_EXIT Worker exit detail: Worker exits by an user request. Worker exits with "
    "an exit code 0. exit_actor() is called."
)
_RAY_KILL = "The actor is dead because it was killed by `ray.kill`."  # ray.kill(actor) mid-call
_INIT_RAISED = (  # __init__ raised ValueError("bad config") (ANSI colour codes as Ray sent them)
    "The actor died because of an error raised in its creation task, \x1b[36mray::A.__init__()\x1b[39m "
    "(pid=8290, ip=192.0.2.2, actor_id=4735c40581bcee121003f44201000000, repr=<probe2.A object at "
    "0x7fd499708b90>)\n           ^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^\n"
    "           ^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^^\n"
    '  File "/tmp/rayprobe/probe2.py", line 8, in __init__\n    raise ValueError("bad config")\n'
    "ValueError: bad config"
)
# not measured (no memory pressure or node loss on a test machine): the GCS's sentences
# and exit type name (WorkerExitType NODE_OUT_OF_MEMORY) as in Ray 2.60's gcs_server
# binary, the exit detail after them made up
_OOM = (
    _PROCESS_DIED
    + "NODE_OUT_OF_MEMORY Worker exit detail: Task was killed due to the node running low on memory."
)
_NODE_DIED = (
    "The actor died because its node has died. Node Id: 5f953a4b53d80923b3d9d6e7b32086fc1096ee0e48796e3e9fdb4880\n"
    "\tthe actor's node was preempted: Node was forcibly preempted"
)


@pytest.mark.parametrize(
    ("message", "reason"),
    [
        (_DIED_HEAD + _CONNECTION_CLOSED, VANISHED),
        (_DIED_HEAD + _SIGTERM, "killed by SIGTERM"),
        (_DIED_HEAD + _SYS_EXIT_3, "exited with status 3"),
        (_DIED_HEAD + _EXIT_ACTOR, "exited with status 0"),
        (_DIED_HEAD + _RAY_KILL, "killed by ray.kill"),
        (_INIT_RAISED, "its __init__ raised ValueError: bad config"),
        (_DIED_HEAD + _OOM, "killed by Ray's memory monitor (its node ran low on memory)"),
        (_DIED_HEAD + _NODE_DIED, "its node died (preempted)"),
        # Ray's words for a cause it has not told before: its "because" line, in one line
        (
            _DIED_HEAD + _PROCESS_DIED + "USER_ERROR Worker exit detail: something new.",
            _PROCESS_DIED + "USER_ERROR Worker exit detail: something new.",
        ),
        # ActorDiedError() without a cause, and ActorUnavailableError: the first line
        (
            "The actor died unexpectedly before finishing this task.",
            "The actor died unexpectedly before finishing this task.",
        ),
        (
            "The actor abc is unavailable: connection lost.\nmore",
            "The actor abc is unavailable: connection lost.",
        ),
        ("", "Ray gave no message"),
    ],
)
def test_ray_actor_death_reason_says_what_ray_knows_in_the_local_backends_words(message, reason):
    assert actor_death_reason(message) == reason


def test_ray_actor_death_reason_is_one_line_of_at_most_300_characters():
    reason = actor_death_reason(_DIED_HEAD + "The actor is dead because" + " of\tthis" * 100)
    assert "\n" not in reason and "\t" not in reason and len(reason) == 300 and reason.endswith("...")


@NEEDS_RAY
def test_ray_actors_give_the_same_rows_survive_faults_and_say_where_they_decoded(tmp_path):
    # in each task: 1 is killed once (its retry passes), 2 hangs; 3 kills its actor every
    # time, by a segfault in one task and os._exit in the other: retried, then a failure row
    faults = ((1, "sigkill:once"), (2, "hang:once"), ("count/3", "segfault"), ("count1/3", "exit"))
    build = FakeBuild(faults=faults, marks=str(tmp_path), episodes=4, tasks=2)
    execution = Execution(
        backend="ray", workers=2, max_retries=1, episode_timeout=5.0, device="auto", rebuild=build
    )
    report = run(build(), tmp_path / "r", execution=execution)
    rows = _rows(report)
    assert len(rows) == 8 and report.executed == 8
    hung = rows[rows["episode_index"] == 2]
    assert hung["failure_reason"].eq("timeout: ran past --episode-timeout 5 s").all()
    # one segfault, one os._exit(3): Ray 2.60 says the same of both (test_ray_actor_death_reason...)
    lost = rows.loc[rows["episode_index"] == 3, "failure_reason"]
    assert len(lost) == 2 and lost.eq(f"worker lost: Ray actor died ({VANISHED}) (tried 2 times)").all()
    others = rows[rows["episode_index"] < 2]
    assert others["success"].all() and others["worker_id"].str.startswith("ray-").all()
    clean = run(FakeBuild(episodes=4, tasks=2)(), tmp_path / "clean")
    expected = _rows(clean)[lambda d: d["episode_index"] < 2]
    _same_results(expected.reset_index(drop=True), others.reset_index(drop=True))
    session = report.run_dir.read_manifest()["execution"][-1]
    assert session["backend"] == "ray" and len(session["worker_threads"]) >= 4
    # --device auto on actors that reserved no GPU (--ray-num-gpus 0): each says it used the CPU
    expected_device = {"requested": "auto", "used": "cpu", "gpu": None, "ray_gpu_ids": []}
    assert all(w["device"] == expected_device for w in session["worker_threads"])


@NEEDS_RAY
def test_ray_actors_run_batches_and_rerun_a_lost_batch_alone(tmp_path):
    # in each task, 3-5 are in flight when episode 4's first decode kills the actor (once)
    build = FakeBuild(faults=((4, "sigkill:once"),), marks=str(tmp_path), episodes=6, tasks=2, batch=True)
    execution = Execution(backend="ray", workers=2, batch_envs=3, episode_timeout=20.0, rebuild=build)
    rows = _rows(run(build(), tmp_path / "r", execution=execution))
    assert len(rows) == 12 and rows["success"].all() and rows["worker_id"].str.startswith("ray-").all()
    assert not rows.duplicated(["task", "episode_index"]).any()
    # the three the lost actor held ran again alone (its events reached the parent before it died)
    assert (rows["batch_envs"] == rows["episode_index"].map(lambda i: 1 if i >= 3 else 3)).all()
    clean = _rows(
        run(FakeBuild(episodes=6, tasks=2, batch=True)(), tmp_path / "c", execution=Execution(batch_envs=3))
    )
    _same_results(clean.drop(columns="batch_envs"), rows.drop(columns="batch_envs"))


def test_rows_a_ray_node_ran_are_that_nodes_machine(tmp_path):
    from results.runs import combined_episodes, load_run

    report = run(FakeBuild(episodes=2, tasks=2)(), tmp_path / "r")
    loaded = load_run(report.run_dir.path)
    episodes = loaded.episodes.copy()
    episodes.loc[episodes["task"] == "count1", "host"] = "node-b"
    df = combined_episodes([type(loaded)(loaded.path, loaded.manifest, episodes)])
    machines = df.groupby("task")["machine"].unique()
    assert machines["count"][0] == loaded.machine
    assert machines["count1"][0] == "node-b | node of a Ray cluster"


MT1 = ["run", "--suite", "metaworld/mt1/reach-v3", "--policy", "random", "--episodes-per-task", "1"]


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--workers", "0"], "--workers must be at least 1, got 0; 1 runs in this process"),
        (["--max-retries", "-1"], "--max-retries must be 0 or more, got -1"),
        (["--episode-timeout", "0"], "--episode-timeout must be a positive, finite number of seconds, got 0"),
        (["--ray-address", "auto"], "--ray-address and --ray-num-gpus apply to --backend ray"),
        (
            ["--backend", "ray", "--ray-address", "127.0.0.1:1"],
            "--ray-address 127.0.0.1:1: cannot reach a Ray cluster there",
        ),
        (["--backend", "ray", "--ray-address", "nowhere"], "expected auto or HOST:PORT"),
    ],
)
def test_bad_backend_flags_exit_2_and_write_nothing(cli, tmp_path, monkeypatch, flags, message):
    if "--backend" in flags and not HAS_RAY:
        pytest.skip("ray is not installed: its address is checked after the package")
    monkeypatch.chdir(tmp_path)
    code, _out, err = cli(*MT1, *flags, "--out", str(tmp_path / "out"))
    assert code == 2 and message in err
    assert list(tmp_path.iterdir()) == []


@NEEDS_RAY
def test_ray_workers_asking_for_gpus_this_machine_lacks_exit_2_and_write_nothing(cli, tmp_path, monkeypatch):
    import torch

    if torch.cuda.is_available():
        pytest.skip("this machine has a GPU for the workers to reserve")
    monkeypatch.chdir(tmp_path)
    flags = ["--backend", "ray", "--device", "cuda", "--ray-num-gpus", "1", "--out", str(tmp_path / "out")]
    code, _out, err = cli(*MT1, *flags)
    assert code == 2 and "this machine's Ray has 0 GPU(s), fewer than one worker reserves" in err
    assert list(tmp_path.iterdir()) == []
    import ray

    assert not ray.is_initialized()  # the local Ray started to ask was stopped again


def test_ray_backend_without_ray_names_the_extra(cli, tmp_path, monkeypatch):
    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name, *a: None if name == "ray" else real(name, *a)
    )
    monkeypatch.chdir(tmp_path)
    code, _out, err = cli(*MT1, "--backend", "ray", "--out", str(tmp_path / "out"))
    assert code == 2 and "pip install 'dvla-harness[ray]'" in err
    assert list(tmp_path.iterdir()) == []
