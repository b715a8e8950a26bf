"""Driving the batched loop (harness/batched.py) for a run: refusing what cannot batch
(`--batch-envs` below 1, a policy or server without act_batch), grouping a run's
episodes into batches (task by task, one policy per batch), and `BatchedRunner`, which
keeps a task's K envs between its policies' batches. The in-process executor
(`execute_batched`) and every worker process and Ray actor (harness/backends/local.py)
use the same runner, so a batch runs the same way wherever it runs.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from typing import Any, TypeVar

import gymnasium as gym

from harness.batched import DONE, batch_events
from harness.episode import EpisodeOutcome, remote_policy
from harness.errors import UsageError
from harness.latency import latency_plan, parse_latency
from harness.nfe import NFECounter
from policies.base import can_batch

T = TypeVar("T")


def check_batching(policies: Sequence[Any], batch_envs: int) -> None:
    """Refuse (exit 2) a batch size below 1, or a policy that cannot batch when K > 1.

    `policies`: the run's PolicyRun entries (spec name and built policy)."""
    if batch_envs < 1:
        raise UsageError(f"--batch-envs must be at least 1, got {batch_envs}; 1 steps one env at a time")
    if batch_envs == 1:
        return
    for p in policies:
        try:
            batchable = can_batch(p.policy)  # a remote policy asks its server
        except ConnectionError as exc:
            raise UsageError(f"policy {p.spec.name}: {exc}") from None
        if not batchable and remote_policy(p.policy) is not None:
            raise UsageError(
                f"policy {p.spec.name}: the server at {p.policy.params.url} cannot decode batches (its "
                "metadata has no act_batch: true; openpi servers and experts cannot); serve a decoder "
                f"with dvla-harness serve, or run with --batch-envs 1 (not {batch_envs})"
            )
        if not batchable:
            raise UsageError(
                f"policy {p.spec.name} cannot batch across environments (--batch-envs {batch_envs}): "
                "it must declare act_batch(episodes, observations) and keep no per-episode state "
                "between chunks (policies/base.py BatchPolicy); run it with --batch-envs 1"
            )


def batch_groups(items: Sequence[T], task: Callable[[T], str], policy: Callable[[T], str]) -> list[list[T]]:
    """`items` (episodes in plan order) as batches: task by task in order of first
    appearance, and within a task one group per policy (a batch serves one policy)."""
    groups: dict[str, dict[str, list[T]]] = {}
    for item in items:
        groups.setdefault(task(item), {}).setdefault(policy(item), []).append(item)
    return [group for by_policy in groups.values() for group in by_policy.values()]


class BatchedRunner:
    """Runs a task's episodes of one policy K at a time (`run_batched`), keeping the K envs
    of the current task for its next policy's batch; used by the in-process executor and
    by each worker process and Ray actor, so a batch runs the same way wherever it runs.

    envs: open envs by task name, shared with an `EpisodeRunner` in a worker (and filled
    by the warm-up or the preflight): the current task's env becomes slot 0, and `release`
    puts it back, so a task never holds more than K envs at once (a LIBERO env holds
    ~0.5 GB). counters: the process's NFE counters by id(PolicyRun), shared likewise.
    """

    def __init__(
        self,
        resolved: Any,
        batch_envs: int,
        traces: bool = False,
        envs: dict[str, gym.Env] | None = None,
        counters: dict[int, NFECounter] | None = None,
    ):
        self.resolved, self.batch_envs, self.traces = resolved, batch_envs, traces
        self.envs = {} if envs is None else envs
        self.own_counters = counters is None
        self.counters = (
            {id(p): NFECounter(p.policy) for p in resolved.policies} if counters is None else counters
        )
        self.task: str | None = None
        self.slot_envs: list[gym.Env | None] = []

    def release(self) -> None:
        """Give the current task's slot 0 env back to `envs` and close the others."""
        if self.task is not None and self.slot_envs and self.slot_envs[0] is not None:
            if self.task in self.envs:
                self.slot_envs[0].close()
            else:
                self.envs[self.task] = self.slot_envs[0]
        for env in self.slot_envs[1:]:
            if env is not None:
                env.close()
        self.task, self.slot_envs = None, []

    def events(self, jobs: Sequence[Any]) -> Iterator[tuple[str, Any]]:
        """`batch_events` over `jobs` (EpisodeJobs of one task and one policy); positions
        index `jobs`, and each outcome carries this batch size."""
        from harness.backends.local import episode_context

        task, policy, suite = jobs[0].task, jobs[0].policy, self.resolved.suite
        if task.name != self.task:
            self.release()
            for name in [n for n in self.envs if n != task.name]:
                self.envs.pop(name).close()  # another task's env (a LIBERO env holds ~0.5 GB)
            self.task, self.slot_envs = task.name, [self.envs.pop(task.name, None)]
        yield from batch_events(
            [job.spec for job in jobs],
            lambda: suite.make_env(task),
            policy.policy,
            self.counters[id(policy)],
            lambda spec, env: episode_context(suite.name, task, spec, env),
            self.batch_envs,
            self.resolved.config.replan_every,
            self.traces,
            self.slot_envs,
            self.resolved.config.out_of_space,
            latency_plan(
                parse_latency(self.resolved.config.inference_latency),
                self.resolved.config.execution,
                suite,
                policy.spec.name,
            ),
        )

    def close(self) -> None:
        self.release()
        while self.envs:
            self.envs.popitem()[1].close()
        if self.own_counters:
            for counter in self.counters.values():
                counter.close()


def execute_batched(
    resolved: Any,
    jobs: Sequence[Any],
    on_done: Callable[[Any, EpisodeOutcome], None],
    traces: bool,
    envs: dict[str, gym.Env],
    batch_envs: int,
) -> None:
    """The in-process executor with --batch-envs K: each task's episodes, one policy after
    another (a batch serves one policy), K envs of the task shared by its policies.

    Policies are interleaved per task, not per episode as unbatched: their timing ratios
    are still taken minutes apart at most, under the same load. `envs` (built by the
    preflight, by task name) become slot 0 of their task.
    """
    from harness.backends.local import HOST, IN_PROCESS

    runner = BatchedRunner(resolved, batch_envs, traces, envs)
    try:
        for group in batch_groups(jobs, lambda job: job.task.name, lambda job: job.policy.config_id):
            for kind, payload in runner.events(group):
                if kind == DONE:
                    index, outcome = payload
                    outcome.host, outcome.worker_id = HOST, IN_PROCESS
                    on_done(group[index], outcome)
    finally:
        runner.close()
