"""Runs a resolved config into a run folder: plan, preflight, open, execute, finish.

1. plan: every episode of the run as a job, in the order task -> episode -> policy, so
   the policies of one comparison are interleaved in time (harness/backends/jobs.py);
2. preflight: each policy that can refuses the suite (its `check_spaces`) on the first
   task's env, before anything is written; the env is handed on to the episodes;
3. open: the run folder, checked, locked and created or continued (harness/run/folder.py);
   on --resume the jobs whose rows are recorded are skipped;
4. execute: the jobs on the chosen backend (harness/backends/), each outcome made into a
   row (harness/run/rows.py) and appended as it ends, before the next episode starts;
5. finish: the speed verdict, the rows compacted into episodes.parquet, the manifest's
   status, whether the run finished, failed or was interrupted.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym

from harness.backends import Execution, Sink, execute
from harness.backends.jobs import EpisodeJob, plan_jobs
from harness.config import ResolvedRun
from harness.episode.outcome import EpisodeOutcome
from harness.episode.plan import ExecutionPlan
from harness.episode.timed import BoundedCalls, CallTimedOut
from harness.errors import HarnessError, UsageError
from harness.run.folder import OpenMode, RunFolder
from harness.run.rows import make_row, run_config_labels, trace_lines
from results.store import RunDir


@dataclass
class RunReport:
    run_dir: RunDir
    run_id: str
    executed: int
    skipped: int
    failed: int
    interrupted: bool = False


def preflight(resolved: ResolvedRun, jobs: list[EpisodeJob], bounded: BoundedCalls) -> dict[str, gym.Env]:
    """Let each policy that can (`check_spaces`) refuse the suite before anything is
    written: a checkpoint trained on another suite's observations would otherwise fail
    every episode alike. Uses the first task's env and returns it, by task name, for the
    episodes to reuse (a LIBERO env takes seconds to build); an env that does not build
    is left to the episodes, which record why. With --episode-timeout each check is held
    to it (`bounded`): a policy that does not answer stops the run (exit 3) naming it,
    with nothing written, where it would otherwise hang it."""
    checks = [p for p in resolved.policies if callable(getattr(p.policy, "check_spaces", None))]
    if not checks or not jobs:
        return {}
    try:
        env = resolved.suite.make_env(jobs[0].task)
    except Exception:
        return {}
    for p in checks:
        try:
            bounded.check_spaces(p.policy, env.observation_space, env.action_space)
        except CallTimedOut:
            env.close()
            raise HarnessError(
                f"policy {p.spec.name} did not answer check_spaces within --episode-timeout {bounded.limit:g} s "
                "(a policy that hangs on its first call); nothing was written"
            ) from None
        except ValueError as exc:
            env.close()
            raise UsageError(
                f"policy {p.spec.name} cannot act in {resolved.suite.name} (task {jobs[0].task.name}): {exc}"
            ) from None
    return {jobs[0].task.name: env}


def run(
    resolved: ResolvedRun,
    out: Path,
    mode: OpenMode = OpenMode.NEW,
    *,
    execution: Execution | None = None,
    traces: bool = False,
    progress: Callable[[int, int], Any] | None = None,
) -> RunReport:
    """Evaluate `resolved` into `out`. `progress(total, skipped)` returns a per-episode callback.

    traces: also write each chunk's decode trace to traces.jsonl. Not part of the config
    (recording changes no decoded token), so it is kept in the manifest and a resumed
    run goes on recording if the run it resumes did.
    """
    execution = execution or Execution()
    jobs = plan_jobs(resolved)
    bounded = BoundedCalls(execution.episode_timeout)
    envs = preflight(resolved, jobs, bounded)
    try:
        folder = RunFolder.open(out, mode, resolved, traces)
        try:
            todo = folder.unrecorded(jobs)
            report = RunReport(
                folder.run_dir, folder.run_id, executed=0, skipped=len(jobs) - len(todo), failed=0
            )
            sink = _sink(folder, resolved, progress(len(todo), report.skipped) if progress else None)
            plan = ExecutionPlan.for_run(resolved, execution.batch_envs, folder.traces)
            try:
                execute(resolved, todo, plan, execution, sink, envs)
            except KeyboardInterrupt:
                report.interrupted = True
                folder.finish("interrupted")
            except BaseException as exc:
                # a failed write (exit 3) or a crash: keep every row, say "failed", then re-raise
                with contextlib.suppress(Exception):  # the first failure is the one to report
                    folder.finish("failed", reason=f"{type(exc).__name__}: {exc}")
                raise
            else:
                folder.finish("finished")
            report.executed, report.failed = folder.counts.executed, folder.counts.failed
            return report
        finally:
            folder.close()
    finally:
        while envs:  # the run stopped before its episodes took them over
            envs.popitem()[1].close()
        # served policies let go of their connections; a later call opens them again
        for p in resolved.policies:
            bounded.close(p.policy)


def _sink(folder: RunFolder, resolved: ResolvedRun, tick: Callable[[bool], Any] | None) -> Sink:
    """Where the backend's reports go: each outcome made into a row (and its traces, and a
    failure's traceback in the log) and appended to the folder as it ends."""
    labels = run_config_labels(resolved)

    def on_episode(job: EpisodeJob, outcome: EpisodeOutcome) -> None:
        failure = None
        if outcome.failure_reason is not None:
            failure = {
                "task": job.task.name,
                "episode_index": job.spec.index,
                "policy": job.policy.spec.name,
                "reason": outcome.failure_reason,
                "traceback": outcome.traceback,
            }
        row = make_row(folder.run_id, resolved, job, outcome, labels)
        folder.append(row, trace_lines(folder.run_id, resolved, job, outcome), failure)
        if tick:
            tick(outcome.success)

    return Sink(
        episode=on_episode,
        session=folder.record_session,
        worker=folder.record_worker,
        warm_up=folder.record_warm_up,
    )
