"""Executors: where a run's episodes are run (this process, worker processes, Ray).

The runner (harness/run/runner.py) plans the episodes, skips what is recorded and writes
every row; an executor only runs episodes and hands each outcome back to the runner's
`on_done` in the parent process, so the run folder keeps a single writer whatever runs
the episodes.

- `local`, 1 worker (the default): this process (harness/backends/local.py), episodes
  one after another, or K at a time in lockstep with --batch-envs K, through the one
  episode loop (harness/episode/loop.py).
- `local`, N workers: N spawned processes (harness/backends/pool.py).
- `ray`: N Ray actors, on this machine or a cluster (harness/backends/ray.py).

The last two share one scheduler (harness/backends/scheduler.py): a task's episodes go
to one worker, all policies interleaved episode by episode as in one process; a worker
holds one episode at a time, so a lost worker loses exactly that episode, which is run
again on a fresh worker up to `max_retries` times and then recorded as a failure row.
With --batch-envs K each worker runs a task's episodes K at a time (one policy per
batch) and says when each starts and ends; the episodes a lost batched worker held (up
to K) are run again, alone, on its replacement (schedule.py says why alone).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import gymnasium as gym

if TYPE_CHECKING:
    from harness.backends.jobs import EpisodeJob
    from harness.backends.local import WorkerSpec
    from harness.config import ResolvedRun
    from harness.episode.outcome import EpisodeOutcome
    from harness.episode.plan import ExecutionPlan

BACKENDS = ("local", "ray")
DEFAULT_MAX_RETRIES = 2


@dataclass
class Execution:
    """How a run's episodes are executed. Not part of the config (its fingerprint): a run
    started with one backend or worker count may be resumed with another, since an
    episode's outcome does not depend on where it ran (only its timing does).

    rebuild: makes the ResolvedRun again inside each worker (policies and envs are not
    sent between processes); None rebuilds from the config with `harness.config.resolve`.
    threads: torch/BLAS threads per worker; None = `harness.threads.default_threads`.
    device: --device for each worker's policies (harness/device.py); None leaves them
      where they were built.
    batch_envs: environments stepped in lockstep, one policy call for them all
      (harness/episode/loop.py), in this process or in each worker.
    """

    backend: str = "local"
    workers: int = 1
    max_retries: int = DEFAULT_MAX_RETRIES
    episode_timeout: float | None = None
    ray_address: str | None = None
    ray_num_gpus: float = 0.0
    threads: int | None = None
    device: str | None = None
    batch_envs: int = 1
    rebuild: Callable[[], ResolvedRun] | None = None

    @property
    def in_process(self) -> bool:
        return self.backend == "local" and self.workers == 1 and self.episode_timeout is None

    def record(self) -> dict[str, Any]:
        """The manifest's record of one session (the run, or one --resume of it)."""
        return {
            "backend": self.backend,
            "workers": self.workers,
            "max_retries": self.max_retries,
            "episode_timeout_s": self.episode_timeout,
            "ray_address": self.ray_address,
            "ray_num_gpus": self.ray_num_gpus if self.backend == "ray" else None,
            "batch_envs": self.batch_envs,
            "worker_threads": [],  # one entry per worker that reported ready (one still starting when the work ran out is not)
        }


def _ignore(_record: Any) -> None:
    return None


@dataclass
class Sink:
    """Where a backend hands what it learns to the one process that writes the run: how
    this session executes (first), each episode's outcome as it ends, each worker's
    record as it starts, this process's warm-up record."""

    episode: Callable[[EpisodeJob, EpisodeOutcome], None]
    session: Callable[[dict[str, Any]], None] = field(default=_ignore)
    worker: Callable[[dict[str, Any]], None] = field(default=_ignore)
    warm_up: Callable[[dict[str, Any] | None], None] = field(default=_ignore)


def execute(
    resolved: ResolvedRun,
    jobs: list[EpisodeJob],
    plan: ExecutionPlan,
    execution: Execution,
    sink: Sink,
    envs: dict[str, gym.Env],
) -> None:
    """Run `jobs` with the chosen backend, handing each outcome to the sink here.
    `envs`: built by the preflight in this process; its episodes take them over, and
    workers (which build their own) leave them to be closed."""
    sink.session(execution.record())
    if execution.in_process:
        from harness.backends.local import execute_in_process

        execute_in_process(resolved, jobs, plan, sink, envs)
        return
    while envs:
        envs.popitem()[1].close()
    if not jobs:
        return
    from harness.backends.scheduler import schedule

    spec = worker_spec(resolved, execution, plan.traces)
    if execution.backend == "ray":
        from harness.backends.ray import RayWorkers

        workers: Any = RayWorkers(spec, execution)
    else:
        from harness.backends.pool import ProcessWorkers

        workers = ProcessWorkers(spec)
    try:
        schedule(jobs, workers, execution, sink.episode, sink.worker)
    finally:
        workers.shutdown()


def worker_spec(resolved: ResolvedRun, execution: Execution, traces: bool) -> WorkerSpec:
    """What each worker of this run starts with: the run rebuilt from its config (with
    what --resume adopted), threads, batching, device and the checkpoint hashes."""
    from functools import partial

    from harness.backends.local import WorkerSpec
    from harness.config import checkpoint_pins, rebuild_from_config, worker_rebuild

    rebuild = worker_rebuild(execution.rebuild or partial(rebuild_from_config, resolved.config), resolved)
    heartbeat = None
    if execution.episode_timeout is not None and execution.batch_envs > 1:
        heartbeat = execution.episode_timeout / 4  # declared stalled only after the limit without a step
    return WorkerSpec(
        rebuild,
        execution.threads,
        execution.workers,
        traces,
        execution.batch_envs,
        heartbeat,
        execution.device,
        checkpoint_pins(resolved),
    )
