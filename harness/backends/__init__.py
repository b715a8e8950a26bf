"""Executors: where a run's episodes are run (this process, worker processes, Ray).

The runner (harness/runner.py) plans the episodes, skips what is recorded and writes
every row; an executor only runs episodes and hands each outcome back to the runner's
`on_done` in the parent process, so the run folder keeps a single writer whatever runs
the episodes.

- `local`, 1 worker (the default): this process, episodes one after another
  (harness/backends/local.py), or K at a time in lockstep with --batch-envs K
  (harness/batched.py).
- `local`, N workers: N spawned processes (harness/backends/pool.py).
- `ray`: N Ray actors, on this machine or a cluster (harness/backends/ray.py).

The last two share one scheduler (harness/backends/schedule.py): a task's episodes go
to one worker, all policies interleaved episode by episode as in one process; a worker
holds one episode at a time, so a lost worker loses exactly that episode, which is run
again on a fresh worker up to `max_retries` times and then recorded as a failure row.
With --batch-envs K each worker runs a task's episodes K at a time (one policy per
batch) and says when each starts and ends; the episodes a lost batched worker held (up
to K) are run again, alone, on its replacement (schedule.py says why alone).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import gymnasium as gym

if TYPE_CHECKING:
    from harness.config import ResolvedRun
    from harness.episode import EpisodeOutcome
    from harness.runner import EpisodeJob
    from results.store import RunDir

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
      (harness/batched.py), in this process or in each worker.
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


def record_execution(run_dir: RunDir, execution: Execution) -> Callable[[dict[str, Any]], None]:
    """Append this session to manifest["execution"]; returns the callback the workers'
    records go through (host, pid, threads), written as each worker reports."""
    from harness.manifest import now

    manifest = run_dir.read_manifest()
    sessions = list(manifest.get("execution") or [])
    sessions.append(execution.record() | {"started_at": now()})
    run_dir.write_manifest(manifest | {"execution": sessions})

    def on_worker(record: dict[str, Any]) -> None:
        manifest = run_dir.read_manifest()
        manifest["execution"][-1]["worker_threads"].append(record)
        run_dir.write_manifest(manifest)
        run_dir.log_event("worker_started", **record)

    return on_worker


def execute(
    resolved: ResolvedRun,
    jobs: list[EpisodeJob],
    on_done: Callable[[EpisodeJob, EpisodeOutcome], None],
    traces: bool,
    envs: dict[str, gym.Env],
    execution: Execution | None = None,
    on_worker: Callable[[dict[str, Any]], None] | None = None,
) -> None:
    """Run `jobs` with the chosen backend, handing each outcome to `on_done` here."""
    from harness.backends.local import execute_local

    execution = execution or Execution()
    if execution.in_process and execution.batch_envs > 1:
        from harness.batch_runner import execute_batched

        execute_batched(resolved, jobs, on_done, traces, envs, execution.batch_envs)
        return
    if execution.in_process:
        execute_local(resolved, jobs, on_done, traces, envs)
        return
    while envs:  # built by preflight in this process; the workers build their own
        envs.popitem()[1].close()
    if not jobs:
        return
    from harness.backends.schedule import schedule

    if execution.backend == "ray":
        from harness.backends.ray import RayWorkers

        workers: Any = RayWorkers(resolved, execution, traces)
    else:
        from harness.backends.pool import ProcessWorkers

        workers = ProcessWorkers(resolved, execution, traces)
    try:
        schedule(jobs, workers, execution, on_done, on_worker or (lambda _record: None))
    finally:
        workers.shutdown()
