"""The laptop backend: one process, episodes one after another, envs reused per task."""

from __future__ import annotations

import traceback
from collections.abc import Callable
from datetime import UTC, datetime
from typing import TYPE_CHECKING

import gymnasium as gym

from adapters.base import EpisodeSpec, TaskSpec
from harness.episode import EpisodeOutcome, run_episode
from harness.nfe import NFECounter
from policies.base import EpisodeContext

if TYPE_CHECKING:
    from harness.config import ResolvedRun
    from harness.runner import EpisodeJob


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


def failed_outcome(exc: BaseException) -> EpisodeOutcome:
    return EpisodeOutcome(
        success=False,
        steps=0,
        chunks=0,
        nfe_total=0,
        action_tokens_total=0,
        policy_time_s=0.0,
        env_time_s=0.0,
        wall_clock_s=0.0,
        started_at=datetime.now(UTC),
        failure_reason=f"{type(exc).__name__}: {exc}",
        traceback=traceback.format_exc(),
    )


def execute_local(
    resolved: ResolvedRun,
    jobs: list[EpisodeJob],
    on_done: Callable[[EpisodeJob, EpisodeOutcome], None],
    traces: bool = False,
    envs: dict[str, gym.Env] | None = None,
) -> None:
    """Run `jobs` in this process, in order, handing each outcome to `on_done`.

    Jobs come task by task, so a task's env is closed when the next task starts: a
    LIBERO env holds ~0.5 GB, and ninety of them open at once would not fit. `envs`
    (already built, by task name) are used and closed like the ones built here.
    """
    envs = {} if envs is None else envs
    counters = {id(p): NFECounter(p.policy) for p in resolved.policies}
    try:
        for job in jobs:
            for name in [n for n in envs if n != job.task.name]:
                envs.pop(name).close()
            try:
                if job.task.name not in envs:
                    envs[job.task.name] = resolved.suite.make_env(job.task)
            except Exception as exc:
                on_done(job, failed_outcome(exc))
                continue
            env = envs[job.task.name]
            context = episode_context(resolved.suite.name, job.task, job.spec, env)
            outcome = run_episode(
                env,
                job.policy.policy,
                counters[id(job.policy)],
                context,
                job.spec,
                resolved.config.replan_every,
                record_traces=traces,
            )
            if outcome.failure_reason is not None:
                envs.pop(job.task.name).close()  # its state is suspect: rebuild next time
            on_done(job, outcome)
    finally:
        while envs:
            envs.popitem()[1].close()
        for counter in counters.values():
            counter.close()
