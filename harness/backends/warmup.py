"""Warm each policy up before its first timed episode, outside every row.

A policy's first call pays one-off costs: torch's lazy initialisation, the first call of
each kernel at each shape, memory the allocator has not handed out yet. On MT10 the
first timed episode's policy time was 3.4-5.2 s against 0.15-0.35 s for the later ones,
so short runs measured start-up and per-run tokens/s swung by up to 10x.
One reset and one act per policy, on an observation drawn from the task's observation
space, runs every pass of a chunk's decode at the shapes the episodes use; its seconds
go to the manifest (`warm_up`, or a worker's record), and it is outside the NFE counter's
`counting()`, so none of
its forward passes is counted in any row.

The observation is a sample of the observation space, not an env reset: an extra reset
could move a simulator whose episodes depend on how many resets came before (LIBERO's
upstream seeding), and the decode's cost depends on the shapes, not the values. Every
shipped policy re-seeds itself in `reset`, so the warm-up changes no later action.
"""

from __future__ import annotations

import copy
import time
from collections.abc import Generator, Sequence
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Any

import gymnasium as gym

from adapters.base import EpisodeSpec, TaskSpec
from harness.episode.context import episode_context
from harness.episode.envs import TaskEnvs

if TYPE_CHECKING:
    from harness.config import PolicyRun

WARM_UP_DEFINITION = (
    "before the first timed episode of this process: per policy, reset on the first "
    "task's first episode, then one act on a sample of its observation space (seed 0), "
    "and with --batch-envs K one act_batch on K copies of it; outside every row, its "
    "forward passes uncounted"
)


def warm_up_observation(space: gym.Space) -> Any:
    """A reproducible observation of the right shapes, drawn without touching the env's own space."""
    space = copy.deepcopy(space)
    space.seed(0)
    return space.sample()


def warm_up_steps(
    policies: Sequence[PolicyRun],
    suite: str,
    task: TaskSpec,
    spec: EpisodeSpec,
    env: gym.Env,
    batch_envs: int = 1,
) -> Generator[PolicyRun, None, dict[str, Any]]:
    """Call each policy once (reset, then act), yielding each policy just before its
    calls, and return the manifest's record of it.

    The yields let a worker tell the scheduler which policy it is calling, so that a
    policy hanging on its first call is stopped by --episode-timeout and charged to an
    episode of that policy (harness/backends/scheduler.py), not to another one.

    batch_envs > 1 (--batch-envs): one act_batch over that many copies of the
    observation too, so the batched shapes' first calls are paid here as well.

    A policy that raises here is recorded with the reason and left to its episodes,
    which record the same failure in their rows (a warm-up is no place to end a run).
    """
    context = episode_context(suite, task, spec, env)
    observation = warm_up_observation(env.observation_space)
    record: dict[str, Any] = {"at": _now(), "definition": WARM_UP_DEFINITION, "policies": []}
    for p in policies:
        yield p
        error = None
        start = time.perf_counter()
        try:
            p.policy.reset([context])
            p.policy.act([observation])
            if batch_envs > 1:
                p.policy.act_batch([context] * batch_envs, [observation] * batch_envs)
        except KeyboardInterrupt:
            raise  # Ctrl-C, SIGTERM: the user wants out
        except BaseException as exc:  # a policy's SystemExit too, as in an episode
            error = f"{type(exc).__name__}: {exc}"
        record["policies"].append(
            {
                "policy": p.spec.name,
                "policy_config_id": p.config_id,
                "seconds": time.perf_counter() - start,
                "error": error,
            }
        )
    return record


def warm_up_run_steps(
    resolved: Any, jobs: Sequence[Any], envs: TaskEnvs, batch_envs: int = 1
) -> Generator[PolicyRun, None, dict[str, Any] | None]:
    """Warm up the policies that have episodes in `jobs`, on the first job's task, with an
    env of it from `envs` (built and left there for the episodes to reuse if missing),
    yielding each policy before its calls (`warm_up_steps`). Returns None when there is
    nothing to run."""
    if not jobs:
        return None
    first = jobs[0]
    try:
        env = envs.peek(first.task)
    except Exception as exc:  # the episodes record why, row by row
        return {
            "at": _now(),
            "skipped": f"the first task's env did not build: {type(exc).__name__}: {exc}",
        }
    running = {id(job.policy) for job in jobs}
    policies = [p for p in resolved.policies if id(p) in running]
    return (yield from warm_up_steps(policies, resolved.suite.name, first.task, first.spec, env, batch_envs))


def _now() -> str:
    return datetime.now(UTC).isoformat()  # as the manifest's other times
