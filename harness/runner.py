"""Runs a resolved config into a run folder: plan, skip what is recorded, execute, store.

Episodes run in the order task -> episode -> policy, so the policies of one comparison
are interleaved in time and share whatever the machine was doing: their timing ratios
are measured side by side. Each row is on disk before the next episode starts.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import gymnasium as gym
import pandas as pd

from adapters.base import EpisodeSpec, TaskSpec
from adapters.simpler_variants import label as variant_label
from harness.backends import Execution, execute, record_execution
from harness.bounded import CallTimedOut, call_within
from harness.config import PolicyRun, ResolvedRun
from harness.cpu_time import is_starved
from harness.episode import EpisodeOutcome
from harness.errors import HarnessError, InterruptedWhileSaving, UsageError
from harness.manifest import now, record_end_calibration
from harness.resume import run_again
from harness.run_folder import acquire, check_output, check_path, io_error, open_run
from harness.warmup import record_warm_up, warm_up_run
from results.labels import config_labels
from results.lock import RunLock
from results.schema import EPISODE_KEY
from results.store import RunDir


@dataclass(frozen=True)
class EpisodeJob:
    policy: PolicyRun
    task: TaskSpec
    spec: EpisodeSpec


@dataclass
class RunReport:
    run_dir: RunDir
    run_id: str
    executed: int
    skipped: int
    failed: int
    interrupted: bool = False


def _key(values: dict[str, Any]) -> tuple:
    """Normalised episode key (pandas gives numpy ints and NaN for nulls)."""
    out = []
    for name in EPISODE_KEY:
        v = values[name]
        if v is None or (isinstance(v, float) and v != v):
            out.append(None)
        elif hasattr(v, "item"):
            out.append(v.item())
        else:
            out.append(v)
    return tuple(out)


def job_key(resolved: ResolvedRun, job: EpisodeJob) -> tuple:
    return _key(
        {
            "suite": resolved.suite.name,
            "task": job.task.name,
            "episode_index": job.spec.index,
            "seed": job.spec.seed,
            "init_state_id": job.spec.init_state_id,
            "variant": variant_label(job.spec.variant),
            "policy": job.policy.spec.name,
            "policy_params": job.policy.params_json,
            "checkpoint_sha256": job.policy.checkpoint_sha256,
        }
    )


def plan(resolved: ResolvedRun) -> list[EpisodeJob]:
    return [
        EpisodeJob(policy, task, spec)
        for task in resolved.tasks
        for spec in resolved.episodes(task)
        for policy in resolved.policies
    ]


def preflight(
    resolved: ResolvedRun, jobs: list[EpisodeJob], limit: float | None = None
) -> dict[str, gym.Env]:
    """Let each policy that can (`check_spaces`) refuse the suite before anything is
    written: a checkpoint trained on another suite's observations would otherwise fail
    every episode alike. Uses the first task's env and returns it, by task name, for the
    episodes to reuse (a LIBERO env takes seconds to build); an env that does not build
    is left to the episodes, which record why. With --episode-timeout (`limit`) each
    check is held to it: a policy that does not answer stops the run (exit 3) naming it,
    with nothing written, where it would otherwise hang it."""
    checks = [(p, getattr(p.policy, "check_spaces", None)) for p in resolved.policies]
    checks = [(p, check) for p, check in checks if callable(check)]
    if not checks or not jobs:
        return {}
    try:
        env = resolved.suite.make_env(jobs[0].task)
    except Exception:
        return {}
    for p, check in checks:
        try:
            call_within(partial(check, env.observation_space, env.action_space), limit)
        except CallTimedOut:
            env.close()
            raise HarnessError(
                f"policy {p.spec.name} did not answer check_spaces within --episode-timeout {limit:g} s "
                "(a policy that hangs on its first call); nothing was written"
            ) from None
        except ValueError as exc:
            env.close()
            raise UsageError(
                f"policy {p.spec.name} cannot act in {resolved.suite.name} (task {jobs[0].task.name}): {exc}"
            ) from None
    return {jobs[0].task.name: env}


def run_config_labels(resolved: ResolvedRun) -> dict[str, str]:
    """The run's configuration labels (results.labels), from every configuration it lists,
    so a row's config_label is the same whichever episodes have run so far."""
    configs = pd.DataFrame(
        [(p.config_id, p.spec.name, p.params_json) for p in resolved.policies],
        columns=["policy_config_id", "policy", "policy_params"],
    )
    return config_labels(configs)


def make_row(
    run_id: str,
    resolved: ResolvedRun,
    job: EpisodeJob,
    out: EpisodeOutcome,
    labels: Mapping[str, str] | None = None,
) -> dict[str, Any]:
    """One episode's row; `labels`: run_config_labels(resolved), worked out once per run."""
    p, task, spec = job.policy, job.task, job.spec
    labels = run_config_labels(resolved) if labels is None else labels
    return {
        "run_id": run_id,
        "suite": resolved.suite.name,
        "suite_version": resolved.suite.version,
        "task": task.name,
        "task_index": task.index,
        "instruction": " | ".join(r["instruction"] for r in out.subtasks)
        if out.subtasks
        else task.instruction,
        "episode_index": spec.index,
        "seed": spec.seed,
        "init_state_id": spec.init_state_id,
        "variant": variant_label(spec.variant),
        "policy": p.spec.name,
        "policy_params": p.params_json,
        "policy_config_id": p.config_id,
        "config_label": labels[p.config_id],
        "checkpoint": p.checkpoint,
        "checkpoint_sha256": p.checkpoint_sha256,
        "replan_every": resolved.config.replan_every,
        "max_steps": task.max_steps,
        "success": out.success,
        "steps": out.steps,
        "chunks": out.chunks,
        "nfe_total": out.nfe_total,
        "nfe_per_chunk": out.nfe_total / out.chunks if out.chunks and out.nfe_total is not None else None,
        "flops_total": out.work.flops,
        "flops_per_chunk": out.work.flops / out.chunks if out.chunks and out.work.flops is not None else None,
        "query_tokens_total": out.work.query_tokens,
        "kv_tokens_total": out.work.kv_tokens,
        "kv_cached_tokens_total": out.work.kv_cached_tokens,
        "action_tokens_total": out.action_tokens_total,
        "tokens_per_s": (
            out.action_tokens_total / out.policy_time_s
            if out.action_tokens_total and out.policy_time_s > 0
            else None
        ),
        "policy_time_s": out.policy_time_s,
        "transport_time_s": out.transport_time_s,
        "policy_cpu_time_s": out.policy_cpu_time_s,
        "starved": is_starved(out.policy_time_s, out.policy_cpu_time_s),
        "env_time_s": out.env_time_s,
        "overhead_s": out.wall_clock_s - out.policy_time_s - out.env_time_s,
        "wall_clock_s": out.wall_clock_s,
        "control_hz": out.steps / out.policy_time_s if out.policy_time_s > 0 else None,
        "loop_hz": out.steps / out.wall_clock_s if out.wall_clock_s > 0 else None,
        "failure_reason": out.failure_reason,
        "out_of_space_rule": resolved.config.out_of_space,
        "actions_out_of_space": out.actions_out_of_space,
        "max_action_excess": out.max_action_excess,
        "inference_latency": resolved.config.inference_latency,
        "execution": resolved.config.execution,
        "delay_steps_mean": out.delay_steps_mean,
        "delay_steps_max": out.delay_steps_max,
        "late_chunks": out.late_chunks,
        "hold_steps": out.hold_steps,
        "started_at": out.started_at,
        "host": out.host,
        "worker_id": out.worker_id,
        "batch_envs": out.batch_envs,
        "speed_reliable": None,  # the run's calibration verdict, set when it finishes (_finish)
        "chain_id": f"{task.name}/{spec.index}" if spec.chain else None,
        "subtasks_completed": (out.subtasks_completed or 0) if spec.chain else None,
        "subtasks": out.subtasks if spec.chain else None,
    }


def trace_lines(run_id: str, resolved: ResolvedRun, job: EpisodeJob, out: EpisodeOutcome) -> list[dict]:
    """traces.jsonl lines of one episode: its key fields, then each chunk's trace."""
    key = {
        "run_id": run_id,
        "suite": resolved.suite.name,
        "task": job.task.name,
        "episode_index": job.spec.index,
        "policy": job.policy.spec.name,
        "policy_config_id": job.policy.config_id,
        "started_at": out.started_at,
    }
    return [key | chunk for chunk in out.traces or ()]


def run(
    resolved: ResolvedRun,
    out: Path,
    *,
    resume: bool = False,
    overwrite: bool = False,
    retry_failed: bool = False,
    progress: Callable[[int, int], Any] | None = None,
    traces: bool = False,
    execution: Execution | None = None,
) -> RunReport:
    """Evaluate `resolved` into `out`. `progress(total, skipped)` returns a per-episode callback.

    traces: also write each chunk's decode trace to traces.jsonl. Not part of the config
    (recording changes no decoded token), so it is kept in the manifest and a resumed
    run goes on recording if the run it resumes did.
    """
    check_path(out, resume, overwrite)
    lock = RunLock(out)  # one writer per folder, held until the manifest says how it ended
    try:
        if out.is_dir():
            acquire(lock)  # a folder another process writes is refused, naming it
        check_output(out, resume, overwrite)
        planned = plan(resolved)
        limit = execution.episode_timeout if execution else None
        envs = preflight(resolved, planned, limit)
        try:
            return _run_planned(
                resolved,
                out,
                planned,
                envs,
                resume,
                overwrite,
                retry_failed,
                progress,
                traces,
                lock,
                execution,
            )
        finally:
            while envs:  # the run stopped before its episodes took them over
                envs.popitem()[1].close()
            close_policies(resolved, limit)
    finally:
        lock.release()


def close_policies(resolved: ResolvedRun, limit: float | None = None) -> None:
    """Let policies that hold something open (a remote policy's connection) let go when
    the run ends; a later call on the same policy opens it again. With --episode-timeout
    (`limit`) a close that does not return in time is abandoned."""
    for p in resolved.policies:
        close = getattr(p.policy, "close", None)
        if callable(close):
            try:
                call_within(close, limit)
            except Exception:  # a policy that fails to let go must not hide the run's outcome
                pass


def _run_planned(
    resolved: ResolvedRun,
    out: Path,
    planned: list[EpisodeJob],
    envs: dict[str, gym.Env],
    resume: bool,
    overwrite: bool,
    retry_failed: bool,
    progress: Callable[[int, int], Any] | None,
    traces: bool,
    lock: RunLock,
    execution: Execution | None = None,
) -> RunReport:
    try:
        run_dir, run_id, recorded = open_run(resolved, out, resume, overwrite, lock)
        manifest = run_dir.read_manifest()
        if traces and not manifest.get("traces"):
            run_dir.write_manifest(manifest | {"traces": True})
    except OSError as exc:
        raise io_error(out, "opening the run folder", exc) from None
    traces = traces or bool(manifest.get("traces"))
    if len(recorded):  # lost workers and servers (and with --retry-failed, every failure) again
        recorded = recorded[~run_again(recorded["failure_reason"], retry_failed)]
    done = {_key(row) for row in recorded[list(EPISODE_KEY)].to_dict("records")} if len(recorded) else set()
    jobs = [job for job in planned if job_key(resolved, job) not in done]
    skipped = len(planned) - len(jobs)
    report = RunReport(run_dir, run_id, executed=0, skipped=skipped, failed=0)
    tick = progress(len(jobs), skipped) if progress else None
    labels = run_config_labels(resolved)

    def on_done(job: EpisodeJob, outcome: EpisodeOutcome) -> None:
        try:
            if outcome.traces:
                run_dir.append_traces(trace_lines(run_id, resolved, job, outcome))
            run_dir.append_episode(make_row(run_id, resolved, job, outcome, labels))
            report.executed += 1
            if outcome.failure_reason is not None:
                report.failed += 1
                run_dir.log_event(
                    "episode_failed",
                    task=job.task.name,
                    episode_index=job.spec.index,
                    policy=job.policy.spec.name,
                    reason=outcome.failure_reason,
                    traceback=outcome.traceback,
                )
        except OSError as exc:
            raise io_error(run_dir.path, "appending an episode's row", exc) from None
        if tick:
            tick(outcome.success)

    try:
        execution = execution or Execution()
        if execution.in_process:  # workers warm their own policies up, each call held to the timeout
            # one-off costs (first calls, lazy init) paid here, outside the rows (harness/warmup.py)
            record_warm_up(run_dir, warm_up_run(resolved, jobs, envs, execution.batch_envs))
        on_worker = record_execution(run_dir, execution)  # backend and workers, per session
        execute(resolved, jobs, on_done, traces, envs, execution, on_worker)
    except KeyboardInterrupt:
        report.interrupted = True
        _finish(run_dir, "interrupted", report)
    except BaseException as exc:
        # a failed write (exit 3) or a crash: keep every row, say "failed", then re-raise
        try:
            _finish(run_dir, "failed", report, reason=f"{type(exc).__name__}: {exc}")
        except Exception:
            pass  # the first failure is the one to report
        raise
    else:
        _finish(run_dir, "finished", report)
    return report


def _episodes_or_none(run_dir: RunDir) -> Any:
    """The run's rows for its speed verdict; None when they cannot be read (the verdict
    then rests on the calibration alone, and the failure that made them unreadable is
    the one reported)."""
    try:
        return run_dir.read_episodes()
    except (OSError, ValueError):
        return None


def _finish(run_dir: RunDir, status: str, report: RunReport, reason: str | None = None) -> None:
    """Compact the rows and record how the run ended; each step is tried even if one
    before it failed (a full disk), and the first failure is raised as a HarnessError."""
    failure: HarnessError | None = None
    stopped = InterruptedWhileSaving(
        f"{run_dir.path}: interrupted while saving; every recorded episode is safe (in "
        "pending.jsonl until episodes.parquet holds it); continue with --resume"
    )
    interrupted = False
    try:
        run_dir.compact()
    except OSError as exc:
        failure = io_error(run_dir.path, "compacting pending.jsonl into episodes.parquet", exc)
        status, reason = "failed", reason or str(failure)
    except KeyboardInterrupt:  # Ctrl-C again: say how it ended (quick), then stop
        interrupted, status = True, "interrupted"
    try:
        manifest = run_dir.read_manifest()
        try:
            if not interrupted:  # seconds of measuring, and the rows' starved episodes counted
                rows = _episodes_or_none(run_dir) if status == "finished" else None
                record_end_calibration(manifest, status, rows)
        except KeyboardInterrupt:
            interrupted, status = True, "interrupted"
        manifest.update(status=status, finished_at=now())
        run_dir.write_manifest(manifest)
    except OSError as exc:
        failure = failure or io_error(run_dir.path, "writing manifest.json", exc)
    except KeyboardInterrupt:
        raise stopped from None
    if failure is None and not interrupted and ("speed_reliable" in manifest or "starvation" in manifest):
        try:  # the rows carry the run's verdict too (null again when none), for the Parquet alone
            run_dir.stamp_rows("speed_reliable", manifest.get("speed_reliable"))
        except OSError as exc:
            failure = io_error(run_dir.path, "writing speed_reliable into episodes.parquet", exc)
        except KeyboardInterrupt:  # the rewrite is atomic: the rows are as they were
            raise stopped from None
    try:
        extra = {"reason": reason} if reason else {}
        run_dir.log_event("run_" + status, executed=report.executed, failed=report.failed, **extra)
    except OSError:
        pass  # the structured log is the least of it
    if failure is not None:
        raise failure
    if interrupted:
        raise stopped
