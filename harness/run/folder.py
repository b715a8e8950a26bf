"""The run folder, as the one process that writes it sees it.

`RunFolder.open` is the only way into a folder for writing. In one of three modes
(new, resume, overwrite; a resume may also run failed episodes again) it refuses what it
must before anything is written (exit 2: a path that is not a writable folder, a folder
that holds something else, another writer, a resume of a different config or of changed
checkpoints), takes the folder's writer lock, clears what a killed writer left, and
writes or continues the manifest. From then on it is the manifest's one owner: the
manifest is held here and written whole (atomically) at the start, at each record a
session adds (warm-up, execution, a worker), and at the end. Rows and traces go through
results/store.py's `RunDir`: appended and flushed as each episode ends, compacted into
episodes.parquet at the end with the run's speed verdict already in every row.

A failed write is a `HarnessError` (exit 3) naming the folder, what was being written
and, for a full disk, the free space; rows recorded before it are kept and --resume
continues.
"""

from __future__ import annotations

import dataclasses
import errno
import os
import shutil
import uuid
from datetime import UTC, datetime
from enum import Enum
from pathlib import Path
from typing import Any

import pandas as pd

from harness.backends.jobs import EpisodeJob, job_key, normalised_key
from harness.config import ResolvedRun, build_config
from harness.errors import HarnessError, InterruptedWhileSaving, UsageError
from harness.run.manifest import build_manifest, now, record_end_calibration
from harness.run.resume import (
    adopt_moved_checkpoints,
    adopt_recorded_params,
    changed_checkpoints,
    config_changes,
    config_data,
    run_again,
)
from results.lock import RunLock, RunLockedError
from results.manifest_check import RESUME_FIELDS
from results.schema import EPISODE_KEY
from results.store import ResultsFileError, RunDir


class OpenMode(Enum):
    """How `run` opens its output folder."""

    NEW = "new"  # absent or empty
    RESUME = "resume"  # the recorded run: only its missing episodes (and lost ones) run
    RETRY_FAILED = "retry_failed"  # as RESUME, and every failed episode runs again
    OVERWRITE = "overwrite"  # what the harness wrote there is replaced

    @classmethod
    def from_flags(cls, resume: bool, overwrite: bool, retry_failed: bool) -> OpenMode:
        if resume and overwrite:
            raise UsageError("--resume and --overwrite contradict each other; pick one")
        if retry_failed and not resume:
            raise UsageError("--retry-failed only makes sense with --resume")
        if resume:
            return cls.RETRY_FAILED if retry_failed else cls.RESUME
        return cls.OVERWRITE if overwrite else cls.NEW

    @property
    def resumes(self) -> bool:
        return self in (OpenMode.RESUME, OpenMode.RETRY_FAILED)


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


def _writable_ancestor(path: Path) -> Path:
    probe = path.absolute()
    while not probe.exists():
        probe = probe.parent
    return probe


def _check_path(out: Path, mode: OpenMode) -> None:
    """The reasons to refuse the output path that do not depend on what the folder holds."""
    if mode is OpenMode.OVERWRITE and out.is_symlink():
        raise UsageError(
            f"--overwrite: {str(out)!r} is a symbolic link (to {os.readlink(out)!r}); refusing to "
            "delete through it; pass the folder itself"
        )
    if out.exists() and not out.is_dir():
        raise UsageError(f"output path {str(out)!r} exists and is not a folder")
    ancestor = _writable_ancestor(out)
    if not ancestor.is_dir() or not os.access(ancestor, os.W_OK | os.X_OK):
        raise UsageError(f"output folder {str(out)!r} is not writable (no write access to {str(ancestor)!r})")


def _check_contents(run_dir: RunDir, mode: OpenMode) -> None:
    """The reasons to refuse what the folder holds (checked with its lock held)."""
    out = run_dir.path
    if mode.resumes:
        if not run_dir.is_run():
            raise UsageError(f"--resume: {str(out)!r} is not a dvla-harness run folder (no manifest.json)")
        return
    if run_dir.is_empty():
        return
    if mode is OpenMode.NEW:
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
        raise UsageError(f"--overwrite: {str(out)!r} is not a dvla-harness run folder; refusing to delete it")


def acquire(lock: RunLock) -> None:
    """Take the run folder's writer lock, or refuse (exit 2) naming the process that holds it."""
    try:
        lock.acquire()
    except RunLockedError as exc:
        raise UsageError(str(exc)) from None
    except OSError as exc:
        raise UsageError(f"cannot lock {str(lock.folder)!r}: {exc}") from None


def _say(line: str) -> None:
    from harness.console import err_console

    err_console.print(line, markup=False, highlight=False, soft_wrap=True)


@dataclasses.dataclass
class Counts:
    """What this session did: episodes run, skipped as recorded, failed."""

    executed: int = 0
    skipped: int = 0
    failed: int = 0


class RunFolder:
    """An open run folder: its writer lock held, its manifest owned, its rows appended."""

    def __init__(
        self, run_dir: RunDir, lock: RunLock, manifest: dict[str, Any], recorded: pd.DataFrame, mode: OpenMode
    ):
        self.run_dir, self.lock, self.manifest, self.recorded = run_dir, lock, manifest, recorded
        self.mode = mode
        self.suite = ""  # the resolved suite's name (an episode key's first field), set by open
        self.counts = Counts()

    @property
    def path(self) -> Path:
        return self.run_dir.path

    @property
    def run_id(self) -> str:
        return str(self.manifest["run_id"])

    @property
    def traces(self) -> bool:
        """Whether this run records decode traces (a resumed run goes on if it did)."""
        return bool(self.manifest.get("traces"))

    # ---- opening ----------------------------------------------------------------------

    @classmethod
    def open(cls, out: Path, mode: OpenMode, resolved: ResolvedRun, traces: bool = False) -> RunFolder:
        """Check, lock and create or continue the folder; nothing is written before every
        check has passed. The lock is released if opening fails."""
        _check_path(out, mode)
        run_dir, lock = RunDir(out), RunLock(out)
        existed = out.is_dir()
        if existed:
            acquire(lock)  # a folder another process writes is refused, naming it
        try:
            _check_contents(run_dir, mode)
            if not existed:
                try:
                    run_dir.create()
                except OSError as exc:
                    raise UsageError(f"cannot create output folder {str(out)!r}: {exc}") from None
                acquire(lock)
                _check_contents(run_dir, mode)  # another process may have written it meanwhile
            if mode.resumes:
                folder = cls._resumed(run_dir, lock, resolved, mode, traces)
            else:
                folder = cls._started(run_dir, lock, resolved, mode, traces)
        except OSError as exc:
            lock.release()
            raise io_error(out, "opening the run folder", exc) from None
        except BaseException:
            lock.release()
            raise
        folder.suite = resolved.suite.name
        return folder

    @classmethod
    def _resumed(
        cls,
        run_dir: RunDir,
        lock: RunLock,
        resolved: ResolvedRun,
        mode: OpenMode,
        traces: bool,
    ) -> RunFolder:
        out = run_dir.path
        try:
            manifest = run_dir.read_manifest(required=RESUME_FIELDS)
            recorded = run_dir.read_episodes()
        except ResultsFileError as exc:
            raise UsageError(f"--resume: {exc}") from None
        changes, extended = config_changes(manifest, resolved)
        if changes:
            raise UsageError(
                f"--resume: {str(out)!r} belongs to a different config ({'; '.join(changes)}); "
                "use another --out, or --overwrite to replace it"
            )
        suites = sorted(set(recorded["suite"]) - {resolved.suite.name}) if len(recorded) else []
        if suites:
            raise UsageError(
                f"--resume: {str(out)!r} holds rows of suite {suites[0]!r}, this config now resolves to "
                f"{resolved.suite.name!r} (a changed default, e.g. LIBERO's seeding); resuming would "
                "mix the two. Name the old one in --suite, or use another --out"
            )
        notices = adopt_recorded_params(manifest, recorded, resolved)
        moved = adopt_moved_checkpoints(manifest, recorded, resolved)
        changed = changed_checkpoints(manifest, recorded, resolved)
        if changed:
            raise UsageError(
                f"--resume: {'; '.join(changed)}; the run's rows came from the old file, so "
                "restore it, or use another --out"
            )
        folder = cls(run_dir, lock, manifest, recorded, mode)
        folder._take_over()
        manifest["resumed_at"].append(now())
        manifest["status"] = "running"
        if traces:
            manifest["traces"] = True
        if extended is not None:
            folder._extend(extended)
        folder.write_manifest()
        run_dir.log_event("run_resumed", recorded=len(recorded))
        for notice in notices:
            _say(notice)
            run_dir.log_event("policy_params_matched_at_defaults", notice=notice)
        for notice in moved:
            _say(notice)
            run_dir.log_event("checkpoint_matched_at_another_path", notice=notice)
        return folder

    @classmethod
    def _started(
        cls,
        run_dir: RunDir,
        lock: RunLock,
        resolved: ResolvedRun,
        mode: OpenMode,
        traces: bool,
    ) -> RunFolder:
        folder = cls(run_dir, lock, {}, pd.DataFrame(), mode)
        folder._take_over()
        if mode is OpenMode.OVERWRITE and not run_dir.is_empty():
            run_dir.remove_recorded()  # only what the harness wrote: _check_contents refused others
        run_id = datetime.now(UTC).strftime("%Y%m%d-%H%M%S-") + uuid.uuid4().hex[:6]
        run_dir.create()
        folder.manifest = build_manifest(resolved, run_id) | ({"traces": True} if traces else {})
        folder.write_manifest()
        run_dir.log_event("run_started", run_id=run_id)
        return folder

    def _extend(self, counts: tuple[int | None, int | None]) -> None:
        """Record that a resumed run now covers more episodes per task (harness/run/resume.py
        says why that is safe): the manifest's config says the new count, and the change is kept."""
        before, after = counts
        manifest = self.manifest
        config = build_config(config_data(manifest["config"]))
        manifest["config"]["episodes_per_task"] = after
        manifest["config_fingerprint"] = dataclasses.replace(config, episodes_per_task=after).fingerprint()
        manifest.setdefault("extended", []).append({"at": now(), "episodes_per_task": [before, after]})
        self.run_dir.log_event("run_extended", episodes_per_task=[before, after])
        shown = "the whole protocol" if after is None else f"{after} episodes per task"
        _say(
            f"--resume: extending the run from {before} to {shown}; the recorded episodes are kept "
            "(an episode is fixed by its index in the protocol) and only the new ones run"
        )

    def _take_over(self) -> None:
        """What a killed writer left behind, cleared before this one writes: a stale lock
        (said in one line), temporary files, a last line cut off mid-write (RunDir.repair)."""
        stale = self.lock.stale_message()
        if stale:
            _say(stale)
        removed = self.run_dir.remove_temporaries()
        if self.run_dir.is_run():
            if stale:
                self.run_dir.log_event("stale_lock_taken_over", holder=self.lock.stale)
            if removed:
                self.run_dir.log_event("temporaries_removed", files=removed)
            self.run_dir.repair()

    # ---- while it runs -----------------------------------------------------------------

    def unrecorded(self, jobs: list[EpisodeJob]) -> list[EpisodeJob]:
        """The jobs this session runs: all but those whose row stays recorded (lost
        workers' and servers' episodes run again, and with --retry-failed every failed one)."""
        recorded = self.recorded
        if not len(recorded):
            return list(jobs)
        recorded = recorded[~run_again(recorded["failure_reason"], self.mode is OpenMode.RETRY_FAILED)]
        done = {normalised_key(row) for row in recorded[list(EPISODE_KEY)].to_dict("records")}
        return [job for job in jobs if job_key(self.suite, job) not in done]

    def write_manifest(self) -> None:
        self.run_dir.write_manifest(self.manifest)

    def record_warm_up(self, record: dict[str, Any] | None) -> None:
        """This session's warm-up, appended to the manifest's `warm_up` list (a resumed run
        warms up again in its new process, and says so in a second entry)."""
        if record is not None:
            self.manifest["warm_up"] = [*(self.manifest.get("warm_up") or []), record]
            self.write_manifest()

    def record_session(self, record: dict[str, Any]) -> None:
        """This session's backend and workers (harness/backends Execution.record), appended
        to the manifest's `execution` list."""
        self.manifest["execution"] = [*(self.manifest.get("execution") or []), record | {"started_at": now()}]
        self.write_manifest()

    def record_worker(self, record: dict[str, Any]) -> None:
        """A worker that reported ready: its host, pid, threads and warm-up."""
        self.manifest["execution"][-1]["worker_threads"].append(record)
        self.write_manifest()
        self.run_dir.log_event("worker_started", **record)

    def append(
        self, row: dict[str, Any], traces: list[dict[str, Any]], failure: dict[str, Any] | None
    ) -> None:
        """One finished episode: its traces, then its row (each flushed before the next
        episode starts), and a failure's traceback in the log."""
        try:
            if traces:
                self.run_dir.append_traces(traces)
            self.run_dir.append_episode(row)
            self.counts.executed += 1
            if failure is not None:
                self.counts.failed += 1
                self.run_dir.log_event("episode_failed", **failure)
        except OSError as exc:
            raise io_error(self.path, "appending an episode's row", exc) from None

    # ---- the end -----------------------------------------------------------------------

    def finish(self, status: str, reason: str | None = None) -> None:
        """Record how the run ended: a finished run's end calibration and speed verdict,
        then the rows compacted into episodes.parquet with the verdict in every row, then
        the manifest's status. Each step is tried even if one before it failed (a full
        disk), and the first failure is raised as a HarnessError; a Ctrl-C while saving
        says how it ended, then stops (InterruptedWhileSaving)."""
        failure: HarnessError | None = None
        stopped = False  # a Ctrl-C while saving
        try:  # seconds of measuring, and the rows' starved episodes counted
            record_end_calibration(self.manifest, status, self._rows() if status == "finished" else None)
        except KeyboardInterrupt:
            stopped, status = True, "interrupted"
        verdict = "speed_reliable" in self.manifest or "starvation" in self.manifest
        stamp = {"speed_reliable": self.manifest.get("speed_reliable")} if verdict and not stopped else None
        try:
            self.run_dir.compact(stamp)
        except OSError as exc:
            failure = io_error(self.path, "compacting pending.jsonl into episodes.parquet", exc)
            status, reason = "failed", reason or str(failure)
        except KeyboardInterrupt:  # Ctrl-C again: say how it ended (quick), then stop
            stopped, status = True, "interrupted"
        self.manifest.update(status=status, finished_at=now())
        try:
            self.write_manifest()
        except OSError as exc:
            failure = failure or io_error(self.path, "writing manifest.json", exc)
        except KeyboardInterrupt:
            raise self._stopped() from None
        try:
            counts = {"executed": self.counts.executed, "failed": self.counts.failed}
            self.run_dir.log_event("run_" + status, **counts, **({"reason": reason} if reason else {}))
        except OSError:
            pass  # the structured log is the least of it
        if failure is not None:
            raise failure
        if stopped:
            raise self._stopped()

    def _rows(self) -> Any:
        """The run's rows for its speed verdict; None when they cannot be read (the verdict
        then rests on the calibration alone, and the failure that made them unreadable is
        the one reported)."""
        try:
            return self.run_dir.read_episodes()
        except (OSError, ValueError):
            return None

    def _stopped(self) -> InterruptedWhileSaving:
        return InterruptedWhileSaving(
            f"{self.path}: interrupted while saving; every recorded episode is safe (in "
            "pending.jsonl until episodes.parquet holds it); continue with --resume"
        )

    def close(self) -> None:
        self.lock.release()
