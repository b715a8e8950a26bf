"""Runs a resolved config into a run folder: plan, skip what is recorded, execute, store.

Episodes run in the order task -> episode -> policy, so the policies of one comparison
are interleaved in time and share whatever the machine was doing: their timing ratios
are measured side by side. Each row is on disk before the next episode starts.
"""

from __future__ import annotations

import errno
import os
import shutil
import traceback
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import gymnasium as gym
import pandas as pd

from adapters.base import EpisodeSpec, TaskSpec
from harness.config import PolicyRun, ResolvedRun
from harness.episode import EpisodeOutcome, run_episode
from harness.errors import HarnessError, UsageError
from harness.manifest import build_manifest, now, record_end_calibration
from harness.nfe import NFECounter
from policies.base import EpisodeContext
from results.lock import RunLock, RunLockedError
from results.schema import EPISODE_KEY
from results.store import ResultsFileError, RunDir


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


def _writable_ancestor(path: Path) -> Path:
    probe = path.absolute()
    while not probe.exists():
        probe = probe.parent
    return probe


def check_output(out: Path, resume: bool, overwrite: bool) -> None:
    """Every reason to refuse the output folder, raised before anything is written."""
    check_path(out, resume, overwrite)
    run_dir = RunDir(out)
    if resume:
        if not run_dir.is_run():
            raise UsageError(f"--resume: {str(out)!r} is not a dvla-harness run folder (no manifest.json)")
    elif not run_dir.is_empty():
        if not overwrite:
            raise UsageError(
                f"output folder {str(out)!r} exists and is not empty; pass --resume to "
                "continue it or --overwrite to replace it"
            )
        foreign = run_dir.foreign_files()
        if foreign:
            more = f" and {len(foreign) - 5} more" if len(foreign) > 5 else ""
            raise UsageError(
                f"--overwrite: {str(out)!r} holds files dvla-harness did not write "
                f"({', '.join(foreign[:5])}{more}); refusing to delete it"
            )
        if not run_dir.is_run():
            raise UsageError(
                f"--overwrite: {str(out)!r} is not a dvla-harness run folder; refusing to delete it"
            )


def check_path(out: Path, resume: bool, overwrite: bool) -> None:
    """The reasons to refuse the output path that do not depend on what the folder holds
    (checked before its writer lock is taken; the rest, under it)."""
    if resume and overwrite:
        raise UsageError("--resume and --overwrite contradict each other; pick one")
    if overwrite and out.is_symlink():
        raise UsageError(
            f"--overwrite: {str(out)!r} is a symbolic link (to {os.readlink(out)!r}); refusing to "
            "delete through it; pass the folder itself"
        )
    if out.exists() and not out.is_dir():
        raise UsageError(f"output path {str(out)!r} exists and is not a folder")
    ancestor = _writable_ancestor(out)
    if not ancestor.is_dir() or not os.access(ancestor, os.W_OK | os.X_OK):
        raise UsageError(f"output folder {str(out)!r} is not writable (no write access to {str(ancestor)!r})")


def preflight(resolved: ResolvedRun, jobs: list[EpisodeJob]) -> dict[str, gym.Env]:
    """Let each policy that can (`check_spaces`) refuse the suite before anything is
    written: a checkpoint trained on another suite's observations would otherwise fail
    every episode alike. Uses the first task's env and returns it, by task name, for the
    episodes to reuse (a LIBERO env takes seconds to build); an env that does not build
    is left to the episodes, which record why."""
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
            check(env.observation_space, env.action_space)
        except ValueError as exc:
            env.close()
            raise UsageError(
                f"policy {p.spec.name} cannot act in {resolved.suite.name} (task {jobs[0].task.name}): {exc}"
            ) from None
    return {jobs[0].task.name: env}


def _config_diff(old: dict[str, Any], new: dict[str, Any]) -> str:
    keys = sorted(set(old) | set(new))
    return "; ".join(f"{k}: {old.get(k)!r} -> {new.get(k)!r}" for k in keys if old.get(k) != new.get(k))


def _changed_checkpoints(
    manifest: dict[str, Any], recorded: pd.DataFrame, resolved: ResolvedRun
) -> list[str]:
    """Policies whose checkpoint file now has other content than when the run recorded it.

    The config names a checkpoint by path; what was evaluated is its content, so a file
    replaced at the same path is another model, and resuming would put two models' rows
    under one policy label."""
    known: dict[tuple[str, str], set[str]] = {}
    for p in manifest.get("policies") or []:
        if isinstance(p, dict) and p.get("checkpoint_sha256"):
            known.setdefault((p.get("name"), p.get("params")), set()).add(p["checkpoint_sha256"])
    if len(recorded):
        cols = ["policy", "policy_params", "checkpoint_sha256"]
        for name, params, digest in recorded[cols].drop_duplicates().itertuples(index=False):
            if isinstance(digest, str) and digest:
                known.setdefault((name, params), set()).add(digest)
    changes = []
    for p in resolved.policies:
        old = sorted(known.get((p.spec.name, p.params_json), set()) - {p.checkpoint_sha256})
        if old:
            changes.append(
                f"policy {p.spec.name}: checkpoint {p.checkpoint!r} had sha256 {old[0][:12]} "
                f"and now has {(p.checkpoint_sha256 or 'none')[:12]}"
            )
    return changes


def io_error(folder: Path, doing: str, exc: OSError) -> HarnessError:
    """One line for a failed write to the run folder; a full disk says so, with the free space."""
    if exc.errno in (errno.ENOSPC, errno.EDQUOT):
        what = "the disk is full" if exc.errno == errno.ENOSPC else "the disk quota is exceeded"
        try:
            free = f"{shutil.disk_usage(folder).free / 1e6:.1f} MB free"
        except OSError:
            free = "free space unknown"
        return HarnessError(
            f"{folder}: {what} ({free}) while {doing}; rows recorded before are kept; "
            "free some space, then continue with --resume"
        )
    return HarnessError(f"{folder}: I/O error while {doing}: {exc}; rows recorded before are kept")


def acquire(lock: RunLock) -> None:
    """Take the run folder's writer lock, or refuse (exit 2) naming the process that holds it."""
    try:
        lock.acquire()
    except RunLockedError as exc:
        raise UsageError(str(exc)) from None
    except OSError as exc:
        raise UsageError(f"cannot lock {str(lock.folder)!r}: {exc}") from None


def open_run(
    resolved: ResolvedRun, out: Path, resume: bool, overwrite: bool, lock: RunLock
) -> tuple[RunDir, str, pd.DataFrame]:
    """Create or reopen the run folder under its writer lock (taken here if the folder is
    new); returns it, the run id and the rows recorded so far."""
    check_output(out, resume, overwrite)
    run_dir = RunDir(out)
    if not lock.held:
        try:
            run_dir.create()
        except OSError as exc:
            raise UsageError(f"cannot create output folder {str(out)!r}: {exc}") from None
        acquire(lock)
        check_output(out, resume, overwrite)  # another process may have written it meanwhile
    if resume:
        try:
            manifest = run_dir.read_manifest()
            recorded = run_dir.read_episodes()
        except ResultsFileError as exc:
            raise UsageError(f"--resume: {exc}") from None
        if manifest.get("config_fingerprint") != resolved.config.fingerprint():
            diff = _config_diff(manifest.get("config", {}), resolved.config.to_dict())
            raise UsageError(
                f"--resume: {str(out)!r} belongs to a different config ({diff}); "
                "use another --out, or --overwrite to replace it"
            )
        suites = sorted(set(recorded["suite"]) - {resolved.suite.name}) if len(recorded) else []
        if suites:
            raise UsageError(
                f"--resume: {str(out)!r} holds rows of suite {suites[0]!r}, this config now resolves to "
                f"{resolved.suite.name!r} (a changed default, e.g. LIBERO's seeding); resuming would "
                "mix the two. Name the old one in --suite, or use another --out"
            )
        changed = _changed_checkpoints(manifest, recorded, resolved)
        if changed:
            raise UsageError(
                f"--resume: {'; '.join(changed)}; the run's rows came from the old file, so "
                "restore it, or use another --out"
            )
    _take_over(run_dir, lock)
    if resume:
        manifest["resumed_at"].append(now())
        manifest["status"] = "running"
        run_dir.write_manifest(manifest)
        run_dir.log_event("run_resumed", recorded=len(recorded))
        return run_dir, manifest["run_id"], recorded
    if overwrite and not run_dir.is_empty():
        run_dir.remove_recorded()  # only what the harness wrote: check_output refused others
    run_id = datetime.now(UTC).strftime("%Y%m%d-%H%M%S-") + uuid.uuid4().hex[:6]
    run_dir.create()
    run_dir.write_manifest(build_manifest(resolved, run_id))
    run_dir.log_event("run_started", run_id=run_id)
    return run_dir, run_id, pd.DataFrame()


def _take_over(run_dir: RunDir, lock: RunLock) -> None:
    """What a killed writer left behind, cleared before this one writes: a stale lock
    (said in one line), temporary files, a last line cut off mid-write (see RunDir.repair)."""
    from harness.console import err_console

    stale = lock.stale_message()
    if stale:
        err_console.print(stale, markup=False, highlight=False, soft_wrap=True)
    removed = run_dir.remove_temporaries()
    if run_dir.is_run():
        if stale:
            run_dir.log_event("stale_lock_taken_over", holder=lock.stale)
        if removed:
            run_dir.log_event("temporaries_removed", files=removed)
        run_dir.repair()


def make_row(run_id: str, resolved: ResolvedRun, job: EpisodeJob, out: EpisodeOutcome) -> dict[str, Any]:
    p, task, spec = job.policy, job.task, job.spec
    return {
        "run_id": run_id,
        "suite": resolved.suite.name,
        "suite_version": resolved.suite.version,
        "task": task.name,
        "task_index": task.index,
        "instruction": task.instruction,
        "episode_index": spec.index,
        "seed": spec.seed,
        "init_state_id": spec.init_state_id,
        "policy": p.spec.name,
        "policy_params": p.params_json,
        "policy_config_id": p.config_id,
        "checkpoint": p.checkpoint,
        "checkpoint_sha256": p.checkpoint_sha256,
        "replan_every": resolved.config.replan_every,
        "max_steps": task.max_steps,
        "success": out.success,
        "steps": out.steps,
        "chunks": out.chunks,
        "nfe_total": out.nfe_total,
        "nfe_per_chunk": out.nfe_total / out.chunks if out.chunks else None,
        "action_tokens_total": out.action_tokens_total,
        "tokens_per_s": (
            out.action_tokens_total / out.policy_time_s
            if out.action_tokens_total and out.policy_time_s > 0
            else None
        ),
        "policy_time_s": out.policy_time_s,
        "env_time_s": out.env_time_s,
        "overhead_s": out.wall_clock_s - out.policy_time_s - out.env_time_s,
        "wall_clock_s": out.wall_clock_s,
        "control_hz": out.steps / out.policy_time_s if out.policy_time_s > 0 else None,
        "loop_hz": out.steps / out.wall_clock_s if out.wall_clock_s > 0 else None,
        "failure_reason": out.failure_reason,
        "started_at": out.started_at,
    }


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


def _failed(exc: BaseException) -> EpisodeOutcome:
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


def execute_local(
    resolved: ResolvedRun,
    jobs: list[EpisodeJob],
    on_done: Callable[[EpisodeJob, EpisodeOutcome], None],
    traces: bool = False,
    envs: dict[str, gym.Env] | None = None,
) -> None:
    """The laptop backend: one process, episodes one after another, envs reused per task.

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
                on_done(job, _failed(exc))
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


def run(
    resolved: ResolvedRun,
    out: Path,
    *,
    resume: bool = False,
    overwrite: bool = False,
    retry_failed: bool = False,
    progress: Callable[[int, int], Any] | None = None,
    traces: bool = False,
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
        envs = preflight(resolved, planned)
        try:
            return _run_planned(
                resolved, out, planned, envs, resume, overwrite, retry_failed, progress, traces, lock
            )
        finally:
            while envs:  # the run stopped before its episodes took them over
                envs.popitem()[1].close()
    finally:
        lock.release()


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
) -> RunReport:
    try:
        run_dir, run_id, recorded = open_run(resolved, out, resume, overwrite, lock)
        manifest = run_dir.read_manifest()
        if traces and not manifest.get("traces"):
            run_dir.write_manifest(manifest | {"traces": True})
    except OSError as exc:
        raise io_error(out, "opening the run folder", exc) from None
    traces = traces or bool(manifest.get("traces"))
    if retry_failed and len(recorded):
        recorded = recorded[recorded["failure_reason"].isna()]
    done = {_key(row) for row in recorded[list(EPISODE_KEY)].to_dict("records")} if len(recorded) else set()
    jobs = [job for job in planned if job_key(resolved, job) not in done]
    skipped = len(planned) - len(jobs)
    report = RunReport(run_dir, run_id, executed=0, skipped=skipped, failed=0)
    tick = progress(len(jobs), skipped) if progress else None

    def on_done(job: EpisodeJob, outcome: EpisodeOutcome) -> None:
        try:
            if outcome.traces:
                run_dir.append_traces(trace_lines(run_id, resolved, job, outcome))
            run_dir.append_episode(make_row(run_id, resolved, job, outcome))
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
        execute_local(resolved, jobs, on_done, traces, envs)
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


def _finish(run_dir: RunDir, status: str, report: RunReport, reason: str | None = None) -> None:
    """Compact the rows and record how the run ended; each step is tried even if one
    before it failed (a full disk), and the first failure is raised as a HarnessError."""
    failure: HarnessError | None = None
    try:
        run_dir.compact()
    except OSError as exc:
        failure = io_error(run_dir.path, "compacting pending.jsonl into episodes.parquet", exc)
        status, reason = "failed", reason or str(failure)
    try:
        manifest = run_dir.read_manifest()
        record_end_calibration(manifest, status)
        manifest.update(status=status, finished_at=now())
        run_dir.write_manifest(manifest)
    except OSError as exc:
        failure = failure or io_error(run_dir.path, "writing manifest.json", exc)
    try:
        extra = {"reason": reason} if reason else {}
        run_dir.log_event("run_" + status, executed=report.executed, failed=report.failed, **extra)
    except OSError:
        pass  # the structured log is the least of it
    if failure is not None:
        raise failure
