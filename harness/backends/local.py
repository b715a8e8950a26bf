"""The laptop backend: one process, episodes one after another, envs reused per task;
and the `Worker` every pool process and Ray actor runs, so an episode runs the same
way wherever it runs."""

from __future__ import annotations

import socket
import time
import traceback
from collections.abc import Callable, Iterator, Sequence
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Any

import gymnasium as gym

from adapters.base import EpisodeSpec, TaskSpec
from harness.episode import EpisodeOutcome, run_episode
from harness.latency import latency_plan, parse_latency
from harness.nfe import NFECounter
from policies.base import EpisodeContext

if TYPE_CHECKING:
    from harness.backends.schedule import JobId as EpisodeJobKey
    from harness.config import ResolvedRun
    from harness.runner import EpisodeJob

HOST = socket.gethostname()  # the `host` column: where an episode ran
IN_PROCESS = "main"  # the `worker_id` of episodes run by the process that writes the run
WARMING = "warming"  # a worker's event: it calls this policy (config id) for its warm-up


def episode_context(suite: str, task: TaskSpec, spec: EpisodeSpec, env: gym.Env) -> EpisodeContext:
    return EpisodeContext(
        suite=suite,
        task=task.name,
        instruction=task.instruction,
        action_space=env.action_space,
        observation_space=env.observation_space,
        max_steps=task.max_steps,
        episode_index=spec.index,
        seed=spec.seed,
        init_state_id=spec.init_state_id,
    )


def failure_outcome(
    reason: str,
    started_at: datetime | None = None,
    trace: str | None = None,
    host: str = "",
    worker_id: str = "",
) -> EpisodeOutcome:
    """The outcome of an episode that did not run to an end: nothing counted, a reason."""
    return EpisodeOutcome(
        success=False,
        steps=0,
        chunks=0,
        nfe_total=0,
        action_tokens_total=0,
        policy_time_s=0.0,
        env_time_s=0.0,
        wall_clock_s=0.0,
        started_at=started_at or datetime.now(UTC),
        failure_reason=reason,
        traceback=trace,
        host=host,
        worker_id=worker_id,
    )


def failed_outcome(exc: BaseException) -> EpisodeOutcome:
    return failure_outcome(f"{type(exc).__name__}: {exc}", trace=traceback.format_exc())


class EpisodeRunner:
    """Runs one episode at a time with the envs and NFE counters of one process.

    A task's env is kept for its next episode and closed when another task's episode
    comes (a LIBERO env holds ~0.5 GB; ninety open at once would not fit), and rebuilt
    after an episode that failed (its state is suspect). Used by the in-process backend
    and by every worker of the pool and Ray backends, so an episode runs the same way
    wherever it runs.
    """

    def __init__(self, resolved: ResolvedRun, traces: bool = False, envs: dict[str, gym.Env] | None = None):
        self.resolved, self.traces = resolved, traces
        self.envs = {} if envs is None else envs
        self.counters = {id(p): NFECounter(p.policy) for p in resolved.policies}

    def run(self, job: EpisodeJob) -> EpisodeOutcome:
        envs, resolved = self.envs, self.resolved
        for name in [n for n in envs if n != job.task.name]:
            envs.pop(name).close()
        try:
            if job.task.name not in envs:
                envs[job.task.name] = resolved.suite.make_env(job.task)
        except Exception as exc:
            return failed_outcome(exc)
        env = envs[job.task.name]
        context = episode_context(resolved.suite.name, job.task, job.spec, env)
        outcome = run_episode(
            env,
            job.policy.policy,
            self.counters[id(job.policy)],
            context,
            job.spec,
            resolved.config.replan_every,
            record_traces=self.traces,
            out_of_space=resolved.config.out_of_space,
            latency=latency_plan(
                parse_latency(resolved.config.inference_latency),
                resolved.config.execution,
                resolved.suite,
                job.policy.spec.name,
            ),
        )
        if outcome.failure_reason is not None:
            envs.pop(job.task.name).close()  # its state is suspect: rebuild next time
        return outcome

    def close(self) -> None:
        while self.envs:
            self.envs.popitem()[1].close()
        for counter in self.counters.values():
            counter.close()


def execute_local(
    resolved: ResolvedRun,
    jobs: list[EpisodeJob],
    on_done: Callable[[EpisodeJob, EpisodeOutcome], None],
    traces: bool = False,
    envs: dict[str, gym.Env] | None = None,
) -> None:
    """Run `jobs` in this process, in order, handing each outcome to `on_done`.

    `envs` (already built, by task name) are used and closed like the ones built here.
    """
    runner = EpisodeRunner(resolved, traces, envs)
    try:
        for job in jobs:
            outcome = runner.run(job)
            outcome.host, outcome.worker_id = HOST, IN_PROCESS
            on_done(job, outcome)
    finally:
        runner.close()


class Worker:
    """A worker's episodes (a pool process or a Ray actor): the run rebuilt, its policies
    warmed up, then the groups of episodes the scheduler (harness/backends/schedule.py)
    sends, each as a stream of events.

    A group sent `alone` runs episode by episode with the `EpisodeRunner`, as without
    batching: every group with --batch-envs 1, and with K > 1 each episode that was in
    flight when its batch's worker was lost or stalled (run alone, a second loss or hang
    names the episode that causes it). Any other group (one task, one policy) runs K at a
    time with the `BatchedRunner`, saying when each episode starts (the scheduler re-runs
    exactly those if the worker is lost) and, with --episode-timeout, that the batch
    still moves at least every `heartbeat_s` seconds.

    The warm-up (harness/warmup.py, `warming`) pays the first calls at the batched shapes
    too, on the run's first task, before the worker reports ready.
    """

    def __init__(
        self,
        resolved: ResolvedRun,
        traces: bool,
        worker_id: str,
        batch_envs: int = 1,
        heartbeat_s: float | None = None,
    ):
        from harness.backends.schedule import index_jobs
        from harness.batch_runner import BatchedRunner

        self.worker_id, self.heartbeat_s = worker_id, heartbeat_s
        self.runner = EpisodeRunner(resolved, traces)
        self.jobs = index_jobs(resolved)
        self.batched = (
            BatchedRunner(resolved, batch_envs, traces, self.runner.envs, self.runner.counters)
            if batch_envs > 1
            else None
        )
        self.resolved, self.batch_envs = resolved, batch_envs
        self.warm_up: dict[str, Any] | None = None

    def warming(self) -> Iterator[tuple[str, Any]]:
        """Warm the policies up (into `self.warm_up`), yielding ("warming",
        policy_config_id) before each one's calls: the scheduler holds each to
        --episode-timeout, so a policy that hangs on its first call cannot hang the run."""
        from harness.warmup import warm_up_run_steps

        steps = warm_up_run_steps(self.resolved, list(self.jobs.values()), self.runner.envs, self.batch_envs)
        while True:
            try:
                p = next(steps)
            except StopIteration as done:
                self.warm_up = done.value
                return
            yield WARMING, p.config_id

    def _placed(self, outcome: EpisodeOutcome) -> EpisodeOutcome:
        outcome.host, outcome.worker_id = HOST, self.worker_id
        return outcome

    def run(self, group: Sequence[EpisodeJobKey], alone: bool) -> Iterator[tuple[str, Any]]:
        """Yields ("started", key), ("stepped", None) and ("done", (key, outcome))."""
        from harness.batched import DONE, STARTED, STEPPED

        if alone or self.batched is None:
            if self.batched is not None:
                self.batched.release()  # its envs back to the runner, K at most per task
            for key in group:
                yield DONE, (key, self._placed(self.runner.run(self.jobs[key])))
            return
        said = time.monotonic()
        for kind, payload in self.batched.events([self.jobs[key] for key in group]):
            if kind == STEPPED and (self.heartbeat_s is None or time.monotonic() - said < self.heartbeat_s):
                continue
            if kind == STARTED:
                payload = group[payload]
            elif kind == DONE:
                index, outcome = payload
                payload = (group[index], self._placed(outcome))
            said = time.monotonic()
            yield kind, payload

    def close(self) -> None:
        if self.batched is not None:
            self.batched.close()
        self.runner.close()
