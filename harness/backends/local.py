"""Running a run's episodes in one process: this one (the laptop backend) or a worker.

`EpisodeRunner` is what every process that runs episodes holds: its open envs, one
`TimedPolicy` (and NFE counter) per policy of the run, and the episode loop
(harness/episode/loop.py). The process that writes the run uses one directly
(`execute_in_process`); each pool process and Ray actor holds one in its `Worker`, so an
episode runs the same way wherever it runs.
"""

from __future__ import annotations

import os
import socket
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import gymnasium as gym

from harness.backends.jobs import EpisodeJob, JobId, batch_groups, index_jobs
from harness.backends.warmup import warm_up_run_steps
from harness.episode.envs import TaskEnvs
from harness.episode.loop import Episode, EpisodeEvent, EpisodeLoop
from harness.episode.plan import ExecutionPlan
from harness.episode.timed import TimedPolicy

if TYPE_CHECKING:
    from harness.backends import Sink
    from harness.config import CheckpointPin, ResolvedRun
    from harness.episode.video import VideoPlan

HOST = socket.gethostname()  # the `host` column: where an episode ran
IN_PROCESS = "main"  # the `worker_id` of episodes run by the process that writes the run
WARMING = "warming"  # a worker's event: it calls this policy (config id) for its warm-up
# How often a worker says how far its running episodes have got (at most; a step that
# takes longer says it when it ends): what a lost or timed-out episode's row records.
PROGRESS_S = 0.25


class EpisodeRunner:
    """A run's episodes in this process: envs kept per task, a counter per policy."""

    def __init__(
        self,
        resolved: ResolvedRun,
        plan: ExecutionPlan,
        worker_id: str,
        envs: dict[str, gym.Env] | None = None,
    ):
        self.resolved, self.plan = resolved, plan
        self.envs = TaskEnvs(resolved.suite.make_env, plan.out_of_space)
        for task, env in (envs or {}).items():
            self.envs.adopt(task, env)
        self.policies = {id(p): TimedPolicy(p.policy, p.spec.name) for p in resolved.policies}
        self.loop = EpisodeLoop(resolved.suite.name, plan, self.envs, worker_id, HOST)

    def episodes(self, jobs: Sequence[EpisodeJob]) -> list[Episode]:
        return [Episode(job.task, job.spec, self.policies[id(job.policy)]) for job in jobs]

    def warm_up(self, jobs: Sequence[EpisodeJob]) -> Iterator[Any]:
        """harness/backends/warmup.py on this process's envs; returns its record."""
        return warm_up_run_steps(self.resolved, jobs, self.envs, self.plan.batch_envs)

    def close(self) -> None:
        self.envs.close()
        for timed in self.policies.values():
            timed.close_counter()


def run_groups(jobs: Sequence[EpisodeJob], batch_envs: int) -> list[list[EpisodeJob]]:
    """The queues the loop takes in turn: every job in plan order, one at a time; or with
    --batch-envs K each task's episodes of one policy (a batch serves one policy), task
    by task, the task's policies one after another (their timing ratios are still taken
    minutes apart at most, under the same load)."""
    if batch_envs == 1:
        return [list(jobs)]
    return batch_groups(jobs, lambda job: job.task.name, lambda job: job.policy.config_id)


def execute_in_process(
    resolved: ResolvedRun, jobs: list[EpisodeJob], plan: ExecutionPlan, sink: Sink, envs: dict[str, gym.Env]
) -> None:
    """Run `jobs` in this process, handing each outcome to the sink as it ends. `envs`
    (built by the preflight) are the loop's first; the policies are warmed up first,
    on the first job's task, outside every row (harness/backends/warmup.py)."""
    runner = EpisodeRunner(resolved, plan, IN_PROCESS, envs)
    envs.clear()
    try:
        sink.warm_up(_drain(runner.warm_up(jobs)))
        for group in run_groups(jobs, plan.batch_envs):
            for index, outcome in runner.loop.run(runner.episodes(group)):
                sink.episode(group[index], outcome)
    finally:
        runner.close()


def _drain(steps: Iterator[Any]) -> Any:
    while True:
        try:
            next(steps)
        except StopIteration as done:
            return done.value


@dataclass(frozen=True)
class WorkerSpec:
    """What every worker of a run is started with (a pool process, a Ray actor)."""

    rebuild: Callable[[], ResolvedRun]  # the run rebuilt from its config, --resume's adoptions applied
    threads: int | None  # --threads (None: the default share of the cores)
    workers: int
    traces: bool
    batch_envs: int = 1
    heartbeat_s: float | None = None  # a batched worker says its batch still moves this often
    device: str | None = None
    pins: tuple[CheckpointPin, ...] = ()  # the checkpoint content the run hashed
    video: VideoPlan | None = None  # --video: which episodes each worker records


class Worker:
    """A worker's episodes (a pool process or a Ray actor): the run rebuilt, its policies
    warmed up, then the groups of episodes the scheduler (harness/backends/scheduler.py)
    sends, each as a stream of events.

    A group sent `alone` runs one episode at a time, as without batching: every group
    with --batch-envs 1, and with K > 1 each episode that was in flight when its batch's
    worker was lost or stalled (run alone, a second loss or hang names the episode that
    causes it); its ends are sent, and how far it has got every PROGRESS_S seconds. Any
    other group (one task, one policy) runs K at a time, saying when each episode starts
    (the scheduler re-runs exactly those if the worker is lost) and that the batch still
    moves (with --episode-timeout at least every `heartbeat_s` seconds)."""

    def __init__(
        self,
        resolved: ResolvedRun,
        worker_id: str,
        batch_envs: int = 1,
        traces: bool = False,
        heartbeat_s: float | None = None,
        video: VideoPlan | None = None,
    ):
        self.worker_id, self.heartbeat_s = worker_id, heartbeat_s
        plan = ExecutionPlan.for_run(resolved, batch_envs, traces, video)
        self.runner = EpisodeRunner(resolved, plan, worker_id)
        self.jobs = index_jobs(resolved)
        self.warm_up: dict[str, Any] | None = None

    def warming(self) -> Iterator[tuple[str, Any]]:
        """Warm the policies up (into `self.warm_up`), yielding ("warming",
        policy_config_id) before each one's calls: the scheduler holds each to
        --episode-timeout, so a policy that hangs on its first call cannot hang the run."""
        steps = self.runner.warm_up(list(self.jobs.values()))
        while True:
            try:
                p = next(steps)
            except StopIteration as done:
                self.warm_up = done.value
                return
            yield WARMING, p.config_id

    def run(self, group: Sequence[JobId], alone: bool) -> Iterator[tuple[str, Any]]:
        """Yields ("started", id), ("stepped", ((id, Progress), ...)) and ("done", (id,
        outcome)). "stepped" goes out at most every PROGRESS_S seconds (a batch with
        --episode-timeout: every `heartbeat_s`), saying how far each running episode has
        got: the scheduler writes it into the row of an episode whose worker is lost or
        runs past its time."""
        jobs = [self.jobs[key] for key in group]
        said = time.monotonic()
        every = PROGRESS_S if alone or self.heartbeat_s is None else min(PROGRESS_S, self.heartbeat_s)
        for kind, payload in self.runner.loop.events(self.runner.episodes(jobs), alone, steps=True):
            if kind is EpisodeEvent.DONE:
                index, outcome = payload
                payload = (group[index], outcome)
            elif kind is EpisodeEvent.STEPPED:
                if time.monotonic() - said < every:
                    continue
                payload = tuple((group[index], out.progress()) for index, out in payload)  # only when sent
            elif alone:
                continue  # an episode sent alone is known to start
            else:
                payload = group[payload]
            said = time.monotonic()
            yield kind.value, payload

    def close(self) -> None:
        self.runner.close()


def start_worker(
    spec: WorkerSpec, worker_id: str, gpu_ids: list[Any] | None = None
) -> tuple[Worker, dict[str, Any]]:
    """A worker's start, the same in a pool process and a Ray actor: its threads set, the
    checkpoints it loads checked against the run's hashes (before and after loading),
    its policies on --device (`gpu_ids`: what Ray reserved for an actor), then the
    manifest's record of it. Any exception is the worker's failure to start."""
    from harness.config import check_checkpoints
    from harness.device import apply_device, worker_device, worker_device_record
    from harness.threads import apply_threads, threads_record

    apply_threads(spec.threads, spec.workers)  # once, before the policies load torch
    check_checkpoints(spec.pins)  # before loading: the content this run hashed, or stop the run
    resolved = spec.rebuild()
    check_checkpoints(spec.pins, resolved)  # and what was loaded
    if spec.device is not None:  # before the warm-up (a GPU's one-off costs are paid there)
        used = worker_device(spec.device, gpu_ids) if gpu_ids is not None else None
        apply_device(resolved.policies, spec.device, used=used)
    worker = Worker(resolved, worker_id, spec.batch_envs, spec.traces, spec.heartbeat_s, spec.video)
    record = {"worker_id": worker_id, "host": HOST, "pid": os.getpid()} | threads_record()
    record["device"] = worker_device_record(gpu_ids)
    return worker, record
